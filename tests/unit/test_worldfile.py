"""World files: the shipped examples load, every dataclass field is reachable from TOML, and every kind of
mistake is a ConfigError that names the file and the exact key."""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.errors import ConfigError
from drivers.sim.raycast import cast_rays, walls_array
from drivers.sim.world import (
    CameraModel,
    Clothing,
    ErrorModel,
    ForwardCameraModel,
    LaserModel,
    Mount,
    Occluder,
    Pose2D,
    RfidModel,
    RobotSpec,
    Scene,
    StrayLight,
    World,
)
from drivers.sim.worldfile import load_world, nominal_camera, parse_world, surveyed_leds

REPO = Path(__file__).resolve().parents[2]
ENV1 = REPO / "examples" / "worlds" / "env1.toml"
OFFICE = REPO / "examples" / "worlds" / "office.toml"


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "world.toml"
    path.write_text(text, encoding="utf-8")
    return path


# -- the shipped worlds --------------------------------------------------------------------------------------
def test_env1_is_the_papers_environment_1(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        world = load_world(ENV1)
    assert not caplog.records, [r.getMessage() for r in caplog.records]
    assert world.source == str(ENV1)
    positions = sorted((led.x_m, led.y_m, led.z_m) for led in world.leds)
    assert positions == sorted(
        [(-0.465, 0.495, 1.5), (-0.460, -0.420, 1.5), (0.460, 0.490, 1.5), (0.480, -0.425, 1.5)]
    )
    freqs = sorted(led.frequency_hz for led in world.leds)
    assert len({(led.frequency_hz, led.duty) for led in world.leds}) == 4
    assert freqs[0] >= 1000 and freqs[-1] <= 6000 and min(np.diff(freqs)) >= 500
    assert world.camera == dataclasses.replace(CameraModel(), frame_rate_hz=world.camera.frame_rate_hz)
    assert world.route and all(abs(x) <= 0.5 and abs(y) <= 0.5 for x, y in world.route)
    assert world.walls
    errors = world.errors
    assert 1.0 < math.hypot(*errors.principal_point_error_px) / 2.56 < 5.0  # ~3 px at 800x600
    assert errors.led_survey_error_m == pytest.approx(0.002)
    assert errors.led_height_error_m == pytest.approx(0.005)
    assert max(abs(a) for a in errors.camera_tilt_rad) == pytest.approx(math.radians(0.2))


def test_office_is_a_building_with_rooms_people_and_a_loop(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        world = load_world(OFFICE)
    assert not caplog.records, [r.getMessage() for r in caplog.records]
    ends = walls_array(world.walls)
    xs, ys = ends[:, [0, 2]], ends[:, [1, 3]]
    assert xs.max() - xs.min() >= 15 and ys.max() - ys.min() >= 10
    signatures = {(led.frequency_hz, led.duty) for led in world.leds}
    assert len(signatures) >= 8
    assert all(2.5 <= led.z_m <= 3.0 for led in world.leds)
    assert len(world.people) == 2 and all(p.tag_id for p in world.people)
    assert len(world.route) >= 4
    # LEDs sharing an id are farther apart than the camera sees (~5.3 m diagonal at 2.6 m).
    same_id = [
        math.hypot(a.x_m - b.x_m, a.y_m - b.y_m)
        for i, a in enumerate(world.leds)
        for b in world.leds[i + 1 :]
        if a.id == b.id
    ]
    assert same_id and min(same_id) > 5.3


def test_office_doors_let_the_laser_through_and_walls_stop_it() -> None:
    world = load_world(OFFICE)
    segments = walls_array(world.walls)
    # From the corridor straight south through S2's door (x 7.0..8.0) to S2's south wall at y = 0.
    through_door = cast_rays((7.5, 6.0), np.array([-math.pi / 2]), segments)
    assert through_door[0] == pytest.approx(6.0)
    # A little west of the door the corridor's south wall (y = 5) stops the beam.
    at_wall = cast_rays((6.0, 6.0), np.array([-math.pi / 2]), segments)
    assert at_wall[0] == pytest.approx(1.0)


def test_the_example_in_the_docs_loads(caplog: pytest.LogCaptureFixture) -> None:
    text = (REPO / "docs" / "world.md").read_text(encoding="utf-8")
    (example,) = re.findall(r"```toml\n(.*?)```", text, re.S)
    with caplog.at_level(logging.WARNING):
        world = parse_world(example, source="docs/world.md")
    assert not caplog.records, [r.getMessage() for r in caplog.records]
    assert world.name == "lab" and len(world.leds) == 7 and world.people and world.route


# -- every field reachable -----------------------------------------------------------------------------------
FULL = """
name = "everything"

[robot]
wheel_radius_m = 0.05
track_m = 0.3
left_id = 3
right_id = 4
max_wheel_radps = 5.0
max_wheel_accel_radps2 = 10.0
radius_m = 0.2
start = { x_m = 0.5, y_m = -0.5, yaw_deg = 90.0 }
camera_mount = { x_m = 0.01, y_m = 0.02, z_m = 0.25, yaw_deg = 180.0, roll_deg = 0.5, pitch_deg = -0.5 }
laser_mount = { x_m = 0.03, y_m = 0.04, z_m = 0.3, yaw_rad = 0.1, roll_rad = 0.01, pitch_rad = 0.02 }
imu_mount = { x_m = -0.01, y_m = -0.02, z_m = 0.05, yaw_rad = 0.2, roll_rad = 0.03, pitch_rad = 0.04 }

[camera]
sensor_width_px = 1280
sensor_height_px = 960
pixel_size_m = 3.75e-6
focal_length_m = 3.6e-3
cx_px = 630.4
cy_px = 485.6
distortion = [-0.1, 0.02, 0.001, -0.001, 0.0005]
t_row_s = 25e-6
exposure_s = 30e-6
output_width_px = 640
output_height_px = 480
frame_rate_hz = 25.0
led_peak_dn = 180.0
black_level_dn = 8.0
read_noise_dn = 2.0
full_well_e = 8000.0
blur_sigma_px = 1.0
radial_falloff = 0.5
bloom_fraction = 0.1
jpeg_quality = 80

[laser]
model = "UTM-30LX"
min_range_mm = 23
max_range_mm = 30000
steps_per_rev = 1440
first_step = 0
last_step = 1080
front_step = 540
scan_rpm = 2400
range_noise_mm = 30.0
dropout = 0.01

[rfid]
protocol = "mercury"
range_m = 0.1
repeat_s = 0.5
antenna_yaws_deg = [45.0, -45.0]
antenna_radius_m = 0.15
beamwidth_deg = 60.0
front_to_back_db = 20.0
rssi_at_1m_dbm = -45.0
sensitivity_dbm = -75.0
wall_reflection = 0.4
scatterers = 4
scatter_amplitude = 0.2
scatter_seed = 7
body_loss_db = 6.0
noise_db = 2.0

[forward_camera]
width_px = 320
height_px = 240
hfov_deg = 60.0
cx_px = 150.0
cy_px = 100.0
frame_rate_hz = 10.0
mount = { x_m = 0.2, y_m = 0.01, z_m = 1.0, yaw_deg = 2.0 }
wall_height_m = 3.0
wall_rgb = [100, 100, 100]
floor_rgb = [90, 90, 90]
ceiling_rgb = [200, 200, 200]
light_variation = 0.2
light_period_s = 5.0
noise_dn = 2.0

[errors]
principal_point_error_px = [1.0, -2.0]
led_survey_error_m = 0.001
led_height_error_m = 0.002
camera_tilt_rad = [0.001, -0.002]
t_row_error_fraction = 0.03
focal_length_error_fraction = -0.01
distortion_error = [0.01, 0.0, 0.0, 0.0, 0.0]
seed = 42

[[leds]]
id = "X"
x_m = 0.1
y_m = 0.2
z_m = 2.0
diameter_m = 0.1
frequency_hz = 2500.0
duty = 0.4
survey_sigma_m = 0.01
brightness = 0.5
dead = true
mapped = false
frequency_drift_hz_per_s = 0.1
frequency_walk_hz_per_sqrt_s = 0.5

[scene]
ambient_dn = 12.0

[[scene.stray_lights]]
x_m = 1.0
y_m = 1.0
z_m = 2.0
shape = "rectangle"
diameter_m = 0.2
width_m = 0.8
length_m = 0.6
yaw_deg = 10.0
brightness = 0.7
flicker_hz = 100.0
flicker_duty = 0.3

[[scene.occluders]]
at = [0.1, 0.25]
fraction = 0.5
angle_deg = 90.0
period_s = 2.0
hidden_s = 0.5
phase_s = 0.25

[[walls]]
points = [[-3.0, -3.0], [3.0, -3.0]]

[[people]]
name = "carol"
tag_id = "ABC"
path = [[1.0, 1.0], [2.0, 1.0]]
speed_mps = 1.1
radius_m = 0.25
yields = false
reaction_s = 0.6
loop = false
start_s = 1.0

[people.clothing]
shirt_rgb = [1, 2, 3]
trousers_rgb = [4, 5, 6]
skin_rgb = [7, 8, 9]
hair_rgb = [1, 1, 1]
pattern = "checks"
pattern_rgb = [9, 9, 9]
pattern_period_m = 0.2
height_m = 1.6

[route]
waypoints = [[0.0, 0.0], [1.0, 0.0]]
speed_mps = 0.35
"""


def test_every_dataclass_field_can_be_set_from_toml(tmp_path: Path) -> None:
    world = load_world(write(tmp_path, FULL))
    sections: list[tuple[Any, Any]] = [
        (world.robot, RobotSpec()),
        (world.camera, CameraModel()),
        (world.laser, LaserModel()),
        (world.rfid, RfidModel()),
        (world.errors, ErrorModel()),
        (world.robot.start, Pose2D(0, 0, 0)),
        (world.robot.camera_mount, Mount()),
        (world.robot.laser_mount, Mount()),
        (world.robot.imu_mount, Mount()),
        (world.leds[0], type(world.leds[0])("", 0, 0, 0)),
        (world.people[0], type(world.people[0])("", "", ())),
        (world.scene, Scene()),
        (world.scene.stray_lights[0], StrayLight(0, 0, 0)),
        (world.scene.occluders[0], Occluder(0)),
        (world.forward_camera, ForwardCameraModel()),
        (world.people[0].clothing, Clothing()),
    ]
    for loaded, default in sections:
        for f in dataclasses.fields(loaded):
            if f.name in (
                "id",
                "x_m",
                "y_m",
                "z_m",
                "name",
                "tag_id",
                "path",
                "led_index",
            ) and not isinstance(loaded, Mount):
                continue  # required fields without defaults
            assert getattr(loaded, f.name) != getattr(default, f.name), f"{type(loaded).__name__}.{f.name}"
    assert world.route_speed_mps == 0.35 and world.route == ((0.0, 0.0), (1.0, 0.0))
    assert world.robot.start.yaw_rad == pytest.approx(math.pi / 2)
    assert world.robot.camera_mount.roll_rad == pytest.approx(math.radians(0.5))
    assert world.name == "everything" and len(world.walls) == 1


def test_an_empty_world_has_the_dataclass_defaults(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        world = load_world(write(tmp_path, ""))
    assert not caplog.records  # the defaults are not the user's doubtful choices
    assert world == World(name="world")
    assert world.source == str(tmp_path / "world.toml")


def test_parse_world_takes_text() -> None:
    world = parse_world('name = "inline"\n[[leds]]\nid = 7\nx_m = 0\ny_m = 0\nz_m = 2.5\n', source="<test>")
    assert world.name == "inline" and world.leds[0].id == "7"


# -- mistakes ------------------------------------------------------------------------------------------------
GRID = "[[led_grids]]\nx0_m = 0\ny0_m = 0\nnx = 2\nny = 1\ndx_m = 2.0\nz_m = 2.5\n"
ROOM = "[[rooms]]\nx_min_m = 0\ny_min_m = 0\nx_max_m = 4\ny_max_m = 3\n"
LED = '[[leds]]\nid = "{id}"\nx_m = {x}\ny_m = 0.0\nz_m = 2.0\nfrequency_hz = {f}\nduty = {d}\n'


def leds(*specs: tuple[str, float, float, float]) -> str:
    return "".join(LED.format(id=i, x=x, f=f, d=d) for i, x, f, d in specs)


BAD: list[tuple[str, str, str]] = [
    # (file text, the key the error must name, a piece of the reason)
    ("name = \n", "", "line 1"),
    ("[camera]\nt_row_s = 1e-5\n[camera]\n", "", "line 3"),
    ("colour = 1\n", "colour", "unknown key"),
    ("[camera]\nt_rows_s = 1e-5\n", "camera.t_rows_s", "did you mean 't_row_s'"),
    ("[camera]\nsensor_width_px = 2048.0\n", "camera.sensor_width_px", "integer"),
    ('[camera]\nt_row_s = "fast"\n', "camera.t_row_s", "number"),
    ("[camera]\nt_row_s = -1e-5\n", "camera.t_row_s", "> 0"),
    ("[camera]\nexposure_s = 0.05\n", "camera.exposure_s", "frame period"),
    ("[camera]\ndistortion = [0.1, 0.0]\n", "camera.distortion", "5 numbers"),
    ("[camera]\ncx_px = 5000.0\n", "camera.cx_px", "on the sensor"),
    ("camera = 3\n", "camera", "table"),
    ("[robot]\nleft_id = 2\nright_id = 2\n", "robot.right_id", "differ"),
    ("[robot]\nleft_id = 300\n", "robot.left_id", "Dynamixel id"),
    (
        "[robot]\nstart = { x_m = 0.0, y_m = 0.0, yaw_rad = 0.1, yaw_deg = 5.0 }\n",
        "robot.start.yaw_deg",
        "not both",
    ),
    ("[robot.start]\nx_m = 0.0\ny_m = 0.0\nyaw_rad = 0.0\nz_m = 1.0\n", "robot.start.z_m", "unknown key"),
    ("[robot.start]\nx_m = 0.0\ny_m = 0.0\n", "robot.start.yaw_rad", "missing (or yaw_deg)"),
    ("[robot.camera_mount]\npitch_deg = 45.0\n", "robot.camera_mount.pitch_deg", "within"),
    ("[laser]\nmin_range_mm = 6000\n", "laser.max_range_mm", "above"),
    ("[laser]\nfront_step = 800\n", "laser.front_step", "first_step <= front_step"),
    ("[laser]\ndropout = 1.0\n", "laser.dropout", "[0, 1)"),
    ('[rfid]\nprotocol = "nfc"\n', "rfid.protocol", "id12la"),
    ("[errors]\ncamera_tilt_deg = [30.0, 0.0]\n", "errors.camera_tilt_deg", "degrees"),
    ("[errors]\nled_survey_error_m = -0.001\n", "errors.led_survey_error_m", ">= 0"),
    (
        "[errors]\nprincipal_point_error_px = [5000.0, 0.0]\n",
        "errors.principal_point_error_px",
        "off the sensor",
    ),
    ("leds = 3\n", "leds", "array of tables"),
    ('[[leds]]\nid = "A"\ny_m = 0.0\nz_m = 2.0\n', "leds[0].x_m", "missing"),
    ('[[leds]]\nid = "A"\nx_m = 0.0\ny_m = 0.0\n', "leds[0].z_m", "led_defaults"),
    ('[[leds]]\nid = "A"\nx_m = nan\ny_m = 0.0\nz_m = 2.0\n', "leds[0].x_m", "finite"),
    ('[[leds]]\nid = "A"\nx_m = "left"\ny_m = 0.0\nz_m = 2.0\n', "leds[0].x_m", "number"),
    ("[[leds]]\nid = true\nx_m = 0\ny_m = 0.0\nz_m = 2.0\n", "leds[0].id", "string"),
    (
        '[[leds]]\nid = "A"\nx_m = 0\ny_m = 0.0\nz_m = 2.0\ncolour = 3\n',
        "leds[0].colour",
        "unknown key",
    ),
    (
        leds(("A", 0.0, 2000, 0.5))
        + '[[leds]]\nid = "B"\nx_m = 1.0\ny_m = 0.0\nz_m = 2.0\ndiameter_m = -0.1\n',
        "leds[1].diameter_m",
        "> 0",
    ),
    (leds(("A", 0.0, 2000, 1.0)), "leds[0].duty", "between 0 and 1"),
    (leds(("A", 0.0, 2000, 0.0)), "leds[0].duty", "between 0 and 1"),
    (
        leds(("A", 0, 1000, 0.5), ("B", 1, 1500, 0.5), ("C", 2, 2500, 0.5), ("D", 3, 20000, 0.5)),
        "leds[3].frequency_hz",
        "Nyquist",
    ),
    (leds(("A", 0.0, 2000, 0.5), ("A", 1.0, 3000, 0.5)), "leds[1]", "one id needs one signature"),
    (leds(("A", 0.0, 2000, 0.5), ("B", 1.0, 2000, 0.5)), "leds[1]", "could not tell them apart"),
    (leds(("A", 0.0, 2000, 0.5), ("B", 0.01, 3000, 0.5)), "leds[1]", "overlaps"),
    (
        "[robot.camera_mount]\nz_m = 2.5\n" + leds(("A", 0.0, 2000, 0.5)),
        "leds[0].z_m",
        "not above the camera",
    ),
    ("[led_defaults]\nduty = 1.5\n", "led_defaults.duty", "between 0 and 1"),
    (
        "[[led_grids]]\nx0_m = 0\ny0_m = 0\nnx = 2\nny = 1\ndx_m = 2.0\nz_m = 2.5\n",
        "led_grids[0].signatures",
        "missing",
    ),
    ("[[led_grids]]\nx0_m = 0\ny0_m = 0\nnx = 0\nny = 1\nz_m = 2.5\n", "led_grids[0].nx", ">= 1"),
    (
        "[[led_grids]]\nx0_m = 0\ny0_m = 0\nnx = 2\nny = 1\ndx_m = 2.0\nz_m = 2.5\n"
        'signatures = [{ id = "A", frequency_hz = 2000.0, duty = 1.2 }]\n',
        "led_grids[0].signatures[0].duty",
        "between 0 and 1",
    ),
    (
        GRID + 'signatures = [{ id = "A", frequency_hz = 2000.0 }, { id = "B", frequency_hz = 16000.0 }]\n',
        "led_grids[0].signatures[1].frequency_hz",
        "Nyquist",
    ),
    (
        GRID.replace("dx_m = 2.0", "dx_m = 0.05")
        + 'signatures = [{ id = "A" }, { id = "B", frequency_hz = 3000.0 }]\n',
        "led_grids[0]",
        "(ix=1, iy=0) overlaps the one at led_grids[0] (ix=0, iy=0)",
    ),
    (GRID + 'row_shift = 5\nsignatures = [{ id = "A" }]\n', "led_grids[0].row_shift", "0..0"),
    ("[[walls]]\npoints = [[0.0, 0.0]]\n", "walls[0].points", "at least 2"),
    ("[[walls]]\npoints = [[0.0, 0.0], [1.0]]\n", "walls[0].points[1]", "point [x, y]"),
    ('[[walls]]\npoints = [[0.0, 0.0], [1.0, 0.0]]\nclosed = "yes"\n', "walls[0].closed", "true or false"),
    (
        "[[polygons]]\npoints = [[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [0.0, 1.0]]\n",
        "polygons[0].points[2]",
        "repeats",
    ),
    ("[[rooms]]\nx_min_m = 0\ny_min_m = 0\nx_max_m = -1\ny_max_m = 3\n", "rooms[0].x_max_m", "above x_min_m"),
    (
        "[[rooms]]\nx_min_m = 0\ny_min_m = 0\nx_max_m = 4\ny_max_m = 3\n"
        'doors = [{ side = "up", offset_m = 1.0 }]\n',
        "rooms[0].doors[0].side",
        "one of",
    ),
    (
        "[[rooms]]\nx_min_m = 0\ny_min_m = 0\nx_max_m = 4\ny_max_m = 3\n"
        'doors = [{ side = "west", offset_m = 2.8, width_m = 0.9 }]\n',
        "rooms[0].doors[0].offset_m",
        "does not fit",
    ),
    (
        ROOM + 'doors = [{ side = "south", offset_m = 1.0 }, { side = "south", offset_m = 1.5 }]\n',
        "rooms[0].doors[1].offset_m",
        "overlaps",
    ),
    (
        ROOM + "[route]\nwaypoints = [[1.0, 1.0], [6.0, 1.0]]\n",
        "route.waypoints[0]",
        "through the wall",
    ),
    (
        "[[rooms]]\nx_min_m = 0\ny_min_m = 0\nx_max_m = 4\ny_max_m = 3\n[route]\n"
        "waypoints = [[1.0, 1.0], [2.0, 1.0]]\nspeed_mps = 0\n",
        "route.speed_mps",
        "> 0",
    ),
    ("[[walls]]\npoints = [[-5.0, 0.05], [5.0, 0.05]]\n", "robot.start", "overlaps the wall"),
    (
        '[[walls]]\npoints = [[2.0, -5.0], [2.0, 5.0]]\n[[people]]\nname = "a"\ntag_id = "1"\n'
        "path = [[1.0, 1.0], [1.0, 2.0], [3.0, 2.0]]\n",
        "people[0].path[1]",
        "through the wall",
    ),
    (
        '[[people]]\nname = "a"\ntag_id = "1"\npath = [[1.0, 1.0]]\n[[people]]\nname = "a"\ntag_id = "2"\n'
        "path = [[2.0, 1.0]]\n",
        "people[1].name",
        "already",
    ),
    (
        '[[people]]\nname = "a"\ntag_id = "1"\npath = [[1.0, 1.0]]\nspeed_mps = -1\n',
        "people[0].speed_mps",
        "> 0",
    ),
    ('[[people]]\nname = "a"\npath = [[1.0, 1.0]]\n', "people[0].tag_id", "missing"),
    (
        '[[people]]\nname = "a"\ntag_id = "1"\npath = [[1.0, 1.0]]\nreaction_s = 2.0\n',
        "people[0].reaction_s",
        "[0, 1.5]",
    ),
    (
        '[[people]]\nname = "a"\ntag_id = "1"\npath = [[1.0, 1.0]]\nyields = 1\n',
        "people[0].yields",
        "true or",
    ),
]


@pytest.mark.parametrize(("text", "key", "reason"), BAD, ids=[b[1] or b[2] for b in BAD])
def test_bad_input_is_a_config_error_naming_file_and_key(
    tmp_path: Path, text: str, key: str, reason: str
) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_world(path)
    err = info.value
    assert err.file == str(path)
    assert err.key == key
    assert reason in err.reason
    assert str(path) in str(err)


def test_a_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read") as info:
        load_world(tmp_path / "nope.toml")
    assert info.value.file == str(tmp_path / "nope.toml")


def test_a_binary_file_is_a_config_error(tmp_path: Path) -> None:
    path = tmp_path / "world.toml"
    path.write_bytes(b'name = "\xff\xfe"\n')
    with pytest.raises(ConfigError, match="UTF-8"):
        load_world(path)


def test_legal_but_doubtful_values_are_warned_about(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    text = (
        "[camera]\nframe_rate_hz = 30.0\n"
        + leds(("A", 0.0, 7000.0, 0.5), ("B", 1.0, 7100.0, 0.55))
        + "[[rooms]]\nx_min_m = -2\ny_min_m = -2\nx_max_m = 2\ny_max_m = 2\n"
        "[route]\nwaypoints = [[0.0, 0.0], [1.95, 0.0]]\n"
    )
    with caplog.at_level(logging.WARNING, logger="drivers.sim.worldfile"):
        load_world(write(tmp_path, text))
    messages = " | ".join(r.getMessage() for r in caplog.records)
    assert "readout" in messages  # 1536 rows x 32 us > 33 ms
    assert "alias after" in messages  # 7 kHz > 6.1 kHz after the 2.56x downsampling
    assert "close signatures" in messages
    assert "closer than the robot's radius" in messages


# -- rooms, grids, and the agent's view ----------------------------------------------------------------------
def test_rooms_become_walls_with_door_gaps(tmp_path: Path) -> None:
    text = (
        "[robot]\nstart = { x_m = 1.0, y_m = 1.0, yaw_rad = 0.0 }\n"
        + ROOM
        + 'doors = [{ side = "south", offset_m = 1.0, width_m = 1.0 },'
        ' { side = "east", offset_m = 2.0, width_m = 0.5 }]\n'
    )
    world = load_world(write(tmp_path, text))
    length = sum(math.hypot(w.x2_m - w.x1_m, w.y2_m - w.y1_m) for w in world.walls)
    assert length == pytest.approx(2 * (4 + 3) - 1.0 - 0.5)
    segments = walls_array(world.walls)
    assert cast_rays((1.0, 1.0), np.array([-math.pi / 2]), segments)[0] == math.inf  # out of the south door
    assert cast_rays((3.0, 1.0), np.array([-math.pi / 2]), segments)[0] == pytest.approx(1.0)
    assert cast_rays((1.0, 2.0), np.array([0.0]), segments)[0] == math.inf  # east door spans y 1.75..2.25


def test_polygons_close_and_polylines_stay_open(tmp_path: Path) -> None:
    text = (
        "[robot]\nstart = { x_m = 9.0, y_m = 9.0, yaw_rad = 0.0 }\n"
        "[[polygons]]\npoints = [[0, 0], [1, 0], [1, 1], [0, 1], [0, 0]]\n"
        "[[walls]]\npoints = [[2, 0], [3, 0], [3, 1]]\n"
        "[[walls]]\npoints = [[4, 0], [5, 0], [5, 1]]\nclosed = true\n"
    )
    world = load_world(write(tmp_path, text))
    assert len(world.walls) == 4 + 2 + 3


def test_led_grid_spreads_signatures(tmp_path: Path) -> None:
    text = (
        "[led_defaults]\nz_m = 2.5\n[[led_grids]]\nx0_m = 0\ny0_m = 0\nnx = 6\nny = 4\n"
        "dx_m = 2.0\ndy_m = 2.0\n"
        "signatures = ["
        + ", ".join(f'{{ id = "S{i}", frequency_hz = {1000 + 500 * i}.0, duty = 0.5 }}' for i in range(5))
        + "]\n[robot]\nstart = { x_m = 1.0, y_m = 1.0, yaw_rad = 0.0 }\n"
    )
    world = load_world(write(tmp_path, text))
    assert len(world.leds) == 24
    grid = {(round(led.x_m / 2), round(led.y_m / 2)): led.id for led in world.leds}
    for (ix, iy), sid in grid.items():
        for nb in ((ix + 1, iy), (ix, iy + 1), (ix + 1, iy + 1), (ix - 1, iy + 1)):
            if nb in grid:
                assert grid[nb] != sid, (ix, iy, nb)


def test_the_agents_view_is_the_truth_bent_by_the_errors() -> None:
    world = load_world(ENV1)
    surveyed = surveyed_leds(world)
    assert surveyed == surveyed_leds(world)  # seeded: the same map every run
    moved = np.array(
        [[s.x_m - t.x_m, s.y_m - t.y_m, s.z_m - t.z_m] for s, t in zip(surveyed, world.leds, strict=True)]
    )
    assert np.all(moved != 0.0)
    assert np.abs(moved[:, :2]).max() < 5 * world.errors.led_survey_error_m
    assert np.abs(moved[:, 2]).max() < 5 * world.errors.led_height_error_m
    nominal = nominal_camera(world)
    true_cx, true_cy = world.camera.principal_point_px
    assert nominal.principal_point_px == pytest.approx((true_cx - 7.7, true_cy + 5.1))
    perfect = dataclasses.replace(world, errors=ErrorModel())
    assert surveyed_leds(perfect) == perfect.leds
    assert nominal_camera(perfect).principal_point_px == perfect.camera.principal_point_px


# -- limits: every count and size is bounded before anything is built from it (issue 17) ------------------
def _zigzag(n: int, x0: float = 100.0) -> str:
    """``n`` distinct [x, y] points far from the robot's start, as a TOML array."""
    return "[" + ", ".join(f"[{x0 + i:.1f}, {100.0 + (i % 2):.1f}]" for i in range(n)) + "]"


def _grid(nx: int, ny: int) -> str:
    return (
        f"[[led_grids]]\nx0_m = 0\ny0_m = 0\nnx = {nx}\nny = {ny}\ndx_m = 0.5\ndy_m = 0.5\nz_m = 3.0\n"
        'signatures = [{ id = "A", frequency_hz = 1000.0 }, { id = "B", frequency_hz = 2500.0 }]\n'
    )


def _people(n: int) -> str:
    return "".join(f'[[people]]\nname = "p{i}"\ntag_id = "{i}"\npath = [[1.0, 1.0]]\n' for i in range(n))


OVER_THE_LIMIT: list[tuple[str, str, str]] = [
    # (file text, the key the error must name, a piece of the reason)
    ("[camera]\nsensor_width_px = 8193\n", "camera.sensor_width_px", "at most 8192"),
    ("[camera]\nsensor_height_px = 8193\n", "camera.sensor_height_px", "at most 8192"),
    ("[camera]\noutput_width_px = 4097\n", "camera.output_width_px", "at most 4096"),
    ("[camera]\noutput_height_px = 9223372036854775807\n", "camera.output_height_px", "at most 4096"),
    ("[camera]\nframe_rate_hz = 1001.0\n", "camera.frame_rate_hz", "at most 1000"),
    ("[laser]\nsteps_per_rev = 10001\n", "laser.steps_per_rev", "at most 10000"),
    ("[laser]\nmax_range_mm = 262144\n", "laser.max_range_mm", "at most 262143"),
    ("[laser]\nscan_rpm = 6001\n", "laser.scan_rpm", "at most 6000"),
    ("[[leds]]\n" * 4097, "leds", "4097 entries, more than the limit of 4096"),
    (_grid(4097, 1), "led_grids[0].nx", "at most 4096"),
    (_grid(1, 4097), "led_grids[0].ny", "at most 4096"),
    (_grid(65, 65), "led_grids[0].ny", "4225 LEDs"),
    (_grid(66, 64), "led_grids[0].nx", "4224 LEDs"),
    (leds(("Z", 50.0, 3000, 0.5)) + _grid(64, 64), "led_grids[0].ny", "the 1 placed before it"),
    (_grid(1, 1) + _grid(64, 64), "led_grids[1].ny", "the 1 placed before it"),
    (GRID + "signatures = [" + "{}, " * 4097 + "]\n", "led_grids[0].signatures", "more than the limit"),
    (f"[[walls]]\npoints = {_zigzag(4097)}\n", "walls[0].points", "4097 points"),
    (f"[[polygons]]\npoints = {_zigzag(4097)}\n", "polygons[0].points", "4097 points"),
    (
        f"[[walls]]\npoints = {_zigzag(4096)}\n[[walls]]\npoints = {_zigzag(3, -100.0)}\n",
        "walls[1].points",
        "4097 wall segments",
    ),
    (f"[[polygons]]\npoints = {_zigzag(4096)}\n" + ROOM, "rooms[0]", "4100 wall segments"),
    ("[[rooms]]\n" * 4097, "rooms", "more than the limit of 4096"),
    (ROOM + "doors = [" + "{}, " * 65 + "]\n", "rooms[0].doors", "more than the limit of 64"),
    (_people(17), "people", "17 entries, more than the limit of 16"),
    (f'[[people]]\nname = "a"\ntag_id = "1"\npath = {_zigzag(257)}\n', "people[0].path", "257 points"),
    (f"[route]\nwaypoints = {_zigzag(257)}\n", "route.waypoints", "257 points"),
]


@pytest.mark.parametrize(
    ("text", "key", "reason"), OVER_THE_LIMIT, ids=[f"{k}:{r}" for _, k, r in OVER_THE_LIMIT]
)
def test_a_count_or_size_over_its_limit_is_a_config_error_naming_the_key(
    text: str, key: str, reason: str
) -> None:
    with pytest.raises(ConfigError) as info:
        parse_world(text, source="big.toml")
    assert (info.value.key, info.value.file) == (key, "big.toml")
    assert reason in info.value.reason
    assert f"big.toml: {key}: " in str(info.value)


@pytest.mark.parametrize(
    "text",
    [
        "[camera]\nsensor_width_px = 8192\nsensor_height_px = 8192\n",
        "[laser]\nsteps_per_rev = 10000\nmax_range_mm = 262143\nscan_rpm = 6000\n",
        _grid(64, 64),
        f'[[people]]\nname = "a"\ntag_id = "1"\npath = {_zigzag(256)}\n[route]\nwaypoints = {_zigzag(256)}\n',
        _people(16),
    ],
    ids=["sensor", "laser", "grid", "paths", "people"],
)
def test_a_world_at_the_limits_loads(text: str) -> None:
    parse_world(text)


def test_the_led_limit_is_4096_whatever_mix_of_leds_and_grids() -> None:
    world = parse_world(leds(("Z", 50.0, 3000, 0.5)) + _grid(63, 65))  # 1 + 4095
    assert len(world.leds) == 4096


@pytest.mark.parametrize("ny", [100_000_000, 2**63 - 1], ids=["1e8", "2**63-1"])
def test_a_huge_led_grid_fails_at_once_without_allocating(ny: int) -> None:
    # Before the bound the loader built every LED: ny = 1e8 took 57 s and 2.95 GB before a MemoryError,
    # 2**63 - 1 never finished. The child is held to 1 GB of address space so that a regression fails as a
    # MemoryError instead of swapping (that cap, not a clock, is what proves nothing was built first); the
    # timeout only keeps a hung loader (2**63 - 1 before the bound) from hanging the suite.
    code = (
        "import resource, sys\n"
        "resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))\n"
        "from drivers.errors import ConfigError\n"
        "from drivers.sim.worldfile import parse_world\n"
        "try:\n"
        "    parse_world(sys.stdin.read(), source='huge.toml')\n"
        "except ConfigError as exc:\n"
        "    print(exc.key, exc.reason, sep='|')\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code],
        input=_grid(1, ny),
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr
    key, reason = proc.stdout.strip().split("|")
    assert key == "led_grids[0].ny" and str(ny) in reason


def test_led_survey_sigma_from_defaults_leds_and_grids(tmp_path: Path) -> None:
    """``survey_sigma_m``: what the agent's LED map states for each LED, from [led_defaults], an LED or a
    grid; the surveyed map the agent is given carries it."""
    world = load_world(
        write(
            tmp_path,
            "[led_defaults]\nz_m = 2.0\nsurvey_sigma_m = 0.025\n"
            '[[leds]]\nid = "A"\nx_m = 0.0\ny_m = 0.0\nfrequency_hz = 1000.0\nduty = 0.5\n'
            '[[leds]]\nid = "B"\nx_m = 1.0\ny_m = 0.0\nfrequency_hz = 2000.0\nduty = 0.5\n'
            "survey_sigma_m = 0.004\n"
            "[[led_grids]]\nx0_m = 0.0\ny0_m = 2.0\nnx = 2\nny = 1\ndx_m = 1.0\nsurvey_sigma_m = 0.01\n"
            'signatures = [{ id = "C", frequency_hz = 3000.0, duty = 0.5 }, '
            '{ id = "D", frequency_hz = 4000.0, duty = 0.5 }]\n'
            "[errors]\nled_survey_error_m = 0.025\n",
        )
    )
    assert [led.survey_sigma_m for led in world.leds] == [0.025, 0.004, 0.01, 0.01]
    assert [led.survey_sigma_m for led in surveyed_leds(world)] == [0.025, 0.004, 0.01, 0.01]
    assert load_world(write(tmp_path, "")).leds == ()


def test_an_led_survey_sigma_out_of_range_names_its_key(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_world(
            write(
                tmp_path,
                '[[leds]]\nid = "A"\nx_m = 0.0\ny_m = 0.0\nz_m = 2.0\nfrequency_hz = 1000.0\nduty = 0.5\n'
                "survey_sigma_m = 2.0\n",
            )
        )
    assert info.value.key == "leds[0].survey_sigma_m", str(info.value)
