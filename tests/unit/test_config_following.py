"""The config of person following: ``[camera.forward]`` (the forward camera) and ``[following]``."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import pytest

from agent.config import load_config, parse_config
from agent.following.coarse import Antenna, RadioModel, default_table
from agent.shipped import WORLDS
from drivers.errors import ConfigError
from drivers.registry import DeviceKind
from tests.helpers import REAL_ROBOT

REAL = REAL_ROBOT  # a minimal real robot: servos only, output on a port
SIM = f'[sim]\nworld = "{WORLDS / "office.toml"}"\n'


def test_a_forward_camera_alone_is_not_taken_for_the_ceiling_camera() -> None:
    config = parse_config(REAL + '[camera.forward]\nbackend = "v4l2"\ndevice = "/dev/video2"\nwidth = 640\n')
    assert DeviceKind.CAMERA not in config.devices
    forward = config.forward_camera
    assert forward is not None and forward.backend == "v4l2" and not forward.critical
    assert forward.options["device"] == "/dev/video2"
    settings = forward.options["settings"]
    assert settings.pixel_format == "BGR8" and settings.width == 640


def test_both_cameras_side_by_side_and_the_simulated_one() -> None:
    config = parse_config(
        REAL
        + '[camera]\nbackend = "genicam"\ncti = "x.cti"\n'
        + '[camera.forward]\nbackend = "genicam"\ncti = "y.cti"\n'
        + "[vlp]\nenabled = false\n"
    )
    assert config.devices[DeviceKind.CAMERA].options["cti"] == "x.cti"
    assert config.forward_camera is not None and config.forward_camera.options["cti"] == "y.cti"
    sim = parse_config(SIM + "[camera.forward]\nframe_rate_hz = 10.0\ncritical = true\n")
    assert (
        sim.forward_camera is not None and sim.forward_camera.backend == "sim" and sim.forward_camera.critical
    )
    assert DeviceKind.CAMERA in sim.devices  # the ceiling camera of the simulated robot is still there
    assert parse_config(SIM).forward_camera is None  # only when asked for


@pytest.mark.parametrize(
    ("text", "key", "words"),
    [
        (REAL + '[camera.forward]\nbackend = "sim"\n', "camera.forward.backend", "needs the simulated robot"),
        (SIM + '[camera.forward]\nbackend = "v4l2"\n', "camera.forward.backend", "'sim'"),
        (REAL + "[camera.forward]\ndevice = 0\n", "camera.forward.backend", "missing"),
        (
            REAL + '[camera.forward]\nbackend = "v4l2"\nexposur_s = 0.01\n',
            "camera.forward.exposur_s",
            "exposure_s",
        ),
        (
            REAL + '[camera.forward]\nbackend = "v4l2"\npixel_format = "YUYV"\n',
            "camera.forward.pixel_format",
            "BGR8",
        ),
        (REAL + "[following]\ncycle_s = 0.0\n", "following.cycle_s", "0.05..5"),
        (REAL + '[following]\nantenna_yaws_deg = ["left"]\n', "following.antenna_yaws_deg", "array"),
        (REAL + '[following]\nrfid_table = "nowhere.toml"\n', "following.rfid_table", "cannot read"),
        (REAL + "[following]\ndistance_m = 0.1\n", "following.distance_m", "0.3..4"),
        (
            REAL + "[following]\ndistance_m = 1.0\nmin_gap_m = 1.2\n",
            "following.min_gap_m",
            "below distance_m",
        ),
        (REAL + "[following]\nmax_speed_mps = 0\n", "following.max_speed_mps", "> 0"),
        (REAL + "[following]\nlost_after_s = 0.0\n", "following.lost_after_s", "0.1..10"),
    ],
)
def test_mistakes_name_their_key(text: str, key: str, words: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(text)
    assert info.value.key == key and words in str(info.value)


def test_following_reads_the_calibrated_table(tmp_path: Path) -> None:
    import tomllib

    table = default_table(RadioModel((Antenna(1, 0.8), Antenna(2, -0.8))))
    lines = []
    for key, value in table.to_dict().items():
        lines.append(f"{key} = {value!r}".replace("'", '"'))
    path = tmp_path / "rfid_table.toml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    assert tomllib.loads(path.read_text())["ports"] == [1, 2]
    config = parse_config(
        REAL
        + textwrap.dedent(
            """
            [following]
            tag_id = "E2000011"
            rfid_table = "rfid_table.toml"
            antenna_yaws_deg = [45.0, -45.0]
            """
        ),
        str(tmp_path / "robot.toml"),
    )
    following = config.following
    assert following.tag_id == "E2000011" and following.table.ports == (1, 2)
    assert following.antenna_yaws_rad == pytest.approx((math.pi / 4, -math.pi / 4))
    path.write_text("ports = [1]\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="not an RFID likelihood table"):
        parse_config(REAL + '[following]\nrfid_table = "rfid_table.toml"\n', str(tmp_path / "robot.toml"))


def test_the_following_example_loads() -> None:
    from agent.shipped import shipped

    config = load_config(shipped("follow.toml"))
    assert config.sim is not None and config.sim.world.name == "follow_straight"
    assert config.devices[DeviceKind.RFID].backend == "mercury"
    assert config.forward_camera is not None and config.forward_camera.backend == "sim"
    assert config.forward_camera.options["render_process"] is True
    assert config.following.tag_id == config.sim.world.people[0].tag_id
    assert config.following.distance_m == 1.0 and config.following.min_gap_m == 0.6
    # The follow worlds' base keeps up with a walking user (0.15 m wheels: 0.99 m/s at 6.6 rad/s).
    assert config.sim.world.robot.wheel_radius_m * config.sim.world.robot.max_wheel_radps > 0.9
    assert config.control.max_speed_mps >= 0.95
