"""The robot config (agent.config): both shipped examples load, and every kind of mistake is a ConfigError
that names the file and the key."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import pytest

from agent.config import OutputFormat, load_config, parse_config
from drivers.errors import ConfigError
from drivers.registry import DeviceKind
from tests.helpers import REAL_ROBOT

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "examples"
OFFICE = EXAMPLES / "worlds" / "office.toml"

REAL = REAL_ROBOT  # a minimal real robot: servos only, output on a port


def write(tmp_path: Path, text: str, name: str = "robot.toml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text), encoding="utf-8")
    return path


def sim_config(extra: str = "") -> str:
    return f'[sim]\nworld = "{OFFICE}"\n' + textwrap.dedent(extra)


# -- the examples ---------------------------------------------------------------------------------------
def test_the_simulated_robot_example_loads() -> None:
    config = load_config(EXAMPLES / "sim.toml")
    assert config.sim is not None
    assert config.sim.world.name == "office"
    assert config.sim.world_file == OFFICE
    assert config.sim.device_priority == 20  # the fakes stand in for hardware: real-time where permitted
    # Every device of the simulated robot, each on the backend its fake speaks.
    assert {k: d.backend for k, d in config.devices.items()} == {
        DeviceKind.CAMERA: "sim",
        DeviceKind.LASER: "urg",
        DeviceKind.SERVOS: "dynamixel",
        DeviceKind.IMU: "mpu6050",
        DeviceKind.RFID: "id12la",
    }
    # Where the devices are comes from the simulation, not the file.
    assert "port" not in config.devices[DeviceKind.SERVOS].options
    assert config.devices[DeviceKind.SERVOS].options["latency_timer_ms"] == 100.0
    assert config.vlp.enabled and config.vlp.intrinsics is None and config.vlp.leds is None
    assert config.slam.enabled and config.slam.particles == 30
    assert config.output.url == "pty" and config.output.format is OutputFormat.FRAME


def test_the_turtlebot3_example_loads() -> None:
    config = load_config(EXAMPLES / "turtlebot3.toml")
    assert config.sim is None
    camera = config.devices[DeviceKind.CAMERA]
    assert camera.backend == "genicam"
    settings = camera.options["settings"]
    assert (settings.width, settings.height, settings.exposure_s) == (800, 600, 20e-6)
    assert config.devices[DeviceKind.LASER].options["url"] == "/dev/urg"
    servos = config.devices[DeviceKind.SERVOS].options
    assert (servos["port"], servos["baudrate"]) == ("/dev/dynamixel", 1_000_000)
    assert config.devices[DeviceKind.IMU].options["bus"] == 1
    assert config.devices[DeviceKind.RFID].backend == "id12la"
    assert not config.devices[DeviceKind.RFID].critical
    assert config.vlp.intrinsics is not None and config.vlp.intrinsics.t_row_s == 32e-6
    assert config.vlp.leds is not None and [led.id for led in config.vlp.leds] == ["L1", "L2", "L3", "L4"]
    assert config.fusion.initial_pose == (0.0, 0.0, 0.0)
    assert math.isclose(config.fusion.initial_sigma_yaw_rad, math.radians(20.0))
    assert config.output.url == "/dev/opencr" and config.output.rate_hz == 30.0
    assert config.slam.map_dir == Path("/var/lib/vlp-agent/maps")


def test_files_the_config_names_are_read(tmp_path: Path) -> None:
    write(
        tmp_path,
        """
        image_width: 640
        image_height: 480
        camera_name: test
        camera_matrix:
          rows: 3
          cols: 3
          data: [500.0, 0, 319.5, 0, 501.0, 239.5, 0, 0, 1]
        distortion_model: plumb_bob
        distortion_coefficients:
          rows: 1
          cols: 5
          data: [0.01, -0.02, 0, 0, 0]
        """,
        "camera_info.yaml",
    )
    write(
        tmp_path,
        """
        [[leds]]
        id = "A"
        x_m = 1.0
        y_m = 2.0
        z_m = 2.5
        frequency_hz = 2000.0
        duty = 0.5
        """,
        "leds.toml",
    )
    path = write(
        tmp_path,
        """
        [camera]
        backend = "v4l2"
        device = "/dev/video0"

        [vlp]
        camera_info = "camera_info.yaml"
        led_map = "leds.toml"

        [vlp.rolling_shutter]
        t_row_s = 30e-6

        [output]
        url = "/dev/ttyS0"
        """,
    )
    config = load_config(path)
    intr = config.vlp.intrinsics
    assert intr is not None
    assert (intr.width_px, intr.height_px, intr.fx_px, intr.fy_px, intr.cx_px, intr.cy_px) == (
        640,
        480,
        500.0,
        501.0,
        319.5,
        239.5,
    )
    assert intr.distortion == (0.01, -0.02, 0.0, 0.0, 0.0) and intr.t_row_s == 30e-6
    assert config.vlp.leds is not None and config.vlp.leds[0].diameter_m == 0.086


def test_a_disabled_device_is_left_out_and_degrees_are_accepted(tmp_path: Path) -> None:
    config = parse_config(
        sim_config(
            """
            [rfid]
            enabled = false
            [fusion]
            initial_pose = { x_m = 1.0, y_m = 2.0, yaw_deg = 90.0 }
            """
        ),
        str(tmp_path / "c.toml"),
    )
    assert DeviceKind.RFID not in config.devices
    assert config.fusion.initial_pose is not None
    assert math.isclose(config.fusion.initial_pose[2], math.pi / 2)


def test_the_vlp_integrity_keys(tmp_path: Path) -> None:
    default = parse_config(sim_config(), str(tmp_path / "c.toml")).vlp
    assert (default.alert_limit_m, default.guarded_sigma_scale, default.fuse_degraded) == (0.10, 3.0, False)
    config = parse_config(
        sim_config(
            """
            [vlp]
            alert_limit_m = 0.25
            guarded_sigma_scale = 0
            fuse_degraded = true
            """
        ),
        str(tmp_path / "c.toml"),
    )
    assert (config.vlp.alert_limit_m, config.vlp.guarded_sigma_scale, config.vlp.fuse_degraded) == (
        0.25,
        0.0,
        True,
    )
    for text, key in (
        ("alert_limit_m = 0", "vlp.alert_limit_m"),
        ("guarded_sigma_scale = 0.5", "vlp.guarded_sigma_scale"),
        ('fuse_degraded = "yes"', "vlp.fuse_degraded"),
    ):
        with pytest.raises(ConfigError) as info:
            parse_config(sim_config(f"[vlp]\n{text}\n"), str(tmp_path / "c.toml"))
        assert info.value.key == key


# -- mistakes --------------------------------------------------------------------------------------------
BAD = [
    # (config text, the key the error names, words of the reason)
    ("[servos\nbackend = 1", "", "not valid TOML"),
    (REAL + "[slma]\nenabled = true\n", "slma", "did you mean 'slam'"),
    (
        REAL.replace('port = "/dev/dynamixel"', 'port = "/dev/dynamixel"\nbaudrat = 57600'),
        "servos.baudrat",
        "baudrate",
    ),
    (
        REAL.replace('port = "/dev/dynamixel"', 'port = "/dev/dynamixel"\nbaudrate = "fast"'),
        "servos.baudrate",
        "integer",
    ),
    (
        REAL.replace('port = "/dev/dynamixel"', 'port = "/dev/dynamixel"\nleft_id = true'),
        "servos.left_id",
        "integer",
    ),
    (REAL.replace('backend = "dynamixel"', 'backend = "dynamixle"'), "servos.backend", "dynamixel"),
    (REAL.replace('port = "/dev/dynamixel"', ""), "servos.port", "required"),
    (
        REAL.replace('port = "/dev/dynamixel"', 'port = "/dev/dynamixel"\nwheel_radius_m = nan'),
        "servos.wheel_radius_m",
        "finite",
    ),
    (REAL + '[laser]\nbackend = "urg"\n', "laser.url", "missing"),
    (REAL + '[camera]\nbackend = "v4l2"\nwidth = 0\n', "camera.width", "positive"),
    (REAL.replace('url = "/dev/ttyS0"', ""), "output.url", "missing"),
    (REAL.replace('url = "/dev/ttyS0"', 'url = "pty"'), "output.url", "[sim]"),
    (REAL + "rate_hz = 500.0\n", "output.rate_hz", "baud"),
    (REAL + 'format = "mavlink"\nmavlink_message = "odometryy"\n', "output.mavlink_message", "odometry"),
    (REAL + "mavlink_sysid = 3\n", "output.mavlink_sysid", "mavlink"),
    (REAL + 'format = "mavlink"\nmavlink_sysid = 0\n', "output.mavlink_sysid", "1..255"),
    (REAL + "[control]\ndeadman_timeout_s = 0.01\n", "control.deadman_timeout_s", "two servo loop periods"),
    (REAL + "[control]\ndeadman_timeout_s = -1.0\n", "control.deadman_timeout_s", "> 0"),
    (REAL + "[fusion]\ngate_probability = 1.5\n", "fusion.gate_probability", "between 0 and 1"),
    (REAL + "[fusion]\ninitial_pose = { x_m = 1.0 }\n", "fusion.initial_pose.y_m", "missing"),
    (
        REAL + "[fusion]\ninitial_pose = { x_m = 1.0, y_m = 0.0, yaw_rad = 0.1, yaw_deg = 5.0 }\n",
        "fusion.initial_pose.yaw_deg",
        "not both",
    ),
    (REAL + "[vlp]\nenabled = true\n", "vlp.enabled", "[camera]"),
    (REAL + "[slam]\nenabled = true\n", "slam.enabled", "[laser]"),
    (REAL + '[slam]\nenabled = false\nmap_mode = "copy"\n', "slam.map_mode", "per_particle"),
    (REAL + '[camera]\nbackend = "v4l2"\n', "vlp.camera_info", "calibration"),
    (
        REAL + '[camera]\nbackend = "v4l2"\n[vlp]\ncamera_info = "missing.yaml"\n',
        "vlp.camera_info",
        "cannot read",
    ),
    (
        REAL
        + '[camera]\nbackend = "v4l2"\n[vlp.intrinsics]\nwidth_px = 800\nheight_px = 600\nfx_px = 500.0\n'
        + "fy_px = 500.0\ncx_px = 400.0\ncy_px = 300.0\n",
        "vlp.rolling_shutter.t_row_s",
        "row time",
    ),
    (
        REAL
        + '[camera]\nbackend = "v4l2"\n[vlp]\nled_map = "x.toml"\n[[vlp.leds]]\nid = "A"\n'
        + "x_m = 0.0\ny_m = 0.0\nz_m = 2.0\nfrequency_hz = 1000.0\nduty = 0.5\n",
        "vlp.leds",
        "not both",
    ),
    (sim_config('[servos]\nport = "/dev/ttyUSB0"\n'), "servos.port", "simulated robot"),
    (sim_config("[servos]\ntrack_m = 0.2\n"), "servos.track_m", "world file"),
    (sim_config('[rfid]\nbackend = "rdm6300"\n'), "rfid.backend", "id12la"),
    (sim_config('[camera]\nbackend = "v4l2"\n'), "camera.backend", "sim"),
    ('[sim]\nworld = "no/such/world.toml"\n', "sim.world", "no such world"),
    ("[sim]\nseed = 1\n", "sim.world", "missing"),
    (sim_config("device_priority = 60\n"), "sim.device_priority", "0..49"),
    ('[output]\nurl = "/dev/ttyS0"\n', "", "no pose source"),
    (REAL + "[scheduling]\nrealtime_priority = 60\n", "scheduling.realtime_priority", "0..49"),
    (REAL + "[scheduling]\nrealtime_priority = 2.5\n", "scheduling.realtime_priority", "whole number"),
    (REAL + "[scheduling]\npriority = 5\n", "scheduling.priority", "unknown"),
    (REAL + "[scheduling]\ncpu_latency_us = -2\n", "scheduling.cpu_latency_us", "-1: no request"),
    (REAL + "[scheduling]\ncpu_latency_us = 0.5\n", "scheduling.cpu_latency_us", "whole number"),
]


@pytest.mark.parametrize(("text", "key", "words"), BAD, ids=[f"{k or 'file'}:{w}" for _, k, w in BAD])
def test_mistakes_name_the_key_and_the_file(tmp_path: Path, text: str, key: str, words: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    error = info.value
    assert error.key == key, str(error)
    assert error.file == str(path), str(error)
    assert words in str(error), str(error)
    assert str(path) in str(error)


LED_MISTAKES = [
    (
        '[[leds]]\nid = "A"\nx_m = 0.0\ny_m = 0.0\nz_m = 2.0\nfrequency_hz = 1000.0\nduty = 1.5\n',
        "leds[0].duty",
    ),
    ('[[leds]]\nid = "A"\nx_m = 0.0\ny_m = 0.0\nfrequency_hz = 1000.0\nduty = 0.5\n', "leds[0].z_m"),
    (
        '[[leds]]\nid = "A"\nx_m = 0.0\ny_m = 0.0\nz_m = 2.0\nfrequency_hz = 1000.0\nduty = 0.5\n'
        '[[leds]]\nid = "A"\nx_m = 3.0\ny_m = 0.0\nz_m = 2.0\nfrequency_hz = 1500.0\nduty = 0.5\n',
        "leds[1]",
    ),
    (
        '[[leds]]\nid = "A"\nx_m = 0.0\ny_m = 0.0\nz_m = 2.0\nfrequency_hz = 1000.0\nduty = 0.5\n'
        "colour = 1\n",
        "leds[0].colour",
    ),
    ("leds = 3\n", "leds"),
    (
        '[[leds]]\nid = "A"\nx_m = 0.0\ny_m = 0.0\nz_m = 2.0\nfrequency_hz = 1000.0\nduty = 0.5\n'
        "survey_sigma_m = -0.01\n",
        "leds[0].survey_sigma_m",
    ),
]


def test_an_led_map_states_each_leds_survey_sigma(tmp_path: Path) -> None:
    """``survey_sigma_m`` per LED in the map file (optional: absent is None, the solver's default)."""
    write(
        tmp_path,
        '[[leds]]\nid = "A"\nx_m = 0.0\ny_m = 0.0\nz_m = 2.0\nfrequency_hz = 1000.0\nduty = 0.5\n'
        "survey_sigma_m = 0.025\n"
        '[[leds]]\nid = "B"\nx_m = 1.0\ny_m = 0.0\nz_m = 2.0\nfrequency_hz = 2000.0\nduty = 0.5\n',
        "leds.toml",
    )
    path = write(
        tmp_path,
        REAL + '[camera]\nbackend = "v4l2"\n[vlp]\nled_map = "leds.toml"\n'
        "[vlp.intrinsics]\nwidth_px = 8\nheight_px = 6\nfx_px = 5.0\nfy_px = 5.0\ncx_px = 4.0\n"
        "cy_px = 3.0\n[vlp.rolling_shutter]\nt_row_s = 3e-5\n",
    )
    leds = load_config(path).vlp.leds
    assert leds is not None
    assert [led.survey_sigma_m for led in leds] == [0.025, None]


@pytest.mark.parametrize(("text", "key"), LED_MISTAKES)
def test_led_map_mistakes_name_the_map_file_and_the_led(tmp_path: Path, text: str, key: str) -> None:
    leds = write(tmp_path, text, "leds.toml")
    path = write(
        tmp_path,
        REAL + '[camera]\nbackend = "v4l2"\n[vlp]\nled_map = "leds.toml"\n'
        "[vlp.intrinsics]\nwidth_px = 8\nheight_px = 6\nfx_px = 5.0\nfy_px = 5.0\ncx_px = 4.0\n"
        "cy_px = 3.0\n[vlp.rolling_shutter]\nt_row_s = 3e-5\n",
    )
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert info.value.key == key, str(info.value)
    assert info.value.file == str(leds)


def test_a_camera_info_that_is_not_one_says_which_file(tmp_path: Path) -> None:
    info = write(tmp_path, "image_width: 640\nimage_height: 480\n", "camera_info.yaml")
    path = write(tmp_path, REAL + '[camera]\nbackend = "v4l2"\n[vlp]\ncamera_info = "camera_info.yaml"\n')
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert (
        err.value.key == "vlp.camera_info"
        and str(info) in str(err.value)
        and "camera_matrix" in str(err.value)
    )


def test_an_unreadable_config_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "absent.toml")
    bad = tmp_path / "latin1.toml"
    bad.write_bytes(b'# caf\xe9\n[output]\nurl = "x"\n')
    with pytest.raises(ConfigError, match="UTF-8"):
        load_config(bad)


# -- limits: every count and size is bounded (issue 17) -----------------------------------------------------
INTRINSICS = (
    "[vlp.intrinsics]\nwidth_px = 800\nheight_px = 600\nfx_px = 500.0\nfy_px = 500.0\ncx_px = 400.0\n"
    "cy_px = 300.0\n[vlp.rolling_shutter]\nt_row_s = 3e-5\n"
)
CAMERA = '[camera]\nbackend = "v4l2"\n'
ONE_LED = '[[{table}]]\nid = "A{i}"\nx_m = {i}.0\ny_m = 0.0\nz_m = 2.0\nfrequency_hz = 1000.0\nduty = 0.5\n'
TOO_MANY_LEDS = "".join(ONE_LED.format(table="vlp.leds", i=i) for i in range(4097))


def _option(table: str, line: str) -> str:
    """REAL with ``line`` added to the device table ``table`` (added with a minimal backend if absent)."""
    if table == "servos":
        return REAL.replace('port = "/dev/dynamixel"', f'port = "/dev/dynamixel"\n{line}')
    backends = {
        "laser": 'backend = "urg"\nurl = "/dev/urg"',
        "rfid": 'backend = "mercury"\nurl = "/dev/rfid"',
        "camera": 'backend = "genicam"\ncti = "x.cti"',
    }
    return (
        REAL
        + f"[{table}]\n{backends[table]}\n{line}\n"
        + ("[vlp]\nenabled = false\n" if table == "camera" else "")
    )


OVER_THE_LIMIT = [
    # (config text, the key the error names, words of the reason)
    (REAL + CAMERA + "width = 8193\n" + INTRINSICS, "camera.width", "at most 8192"),
    (REAL + CAMERA + "height = 9223372036854775807\n" + INTRINSICS, "camera.height", "at most 8192"),
    (
        REAL + CAMERA + INTRINSICS.replace("width_px = 800", "width_px = 8193"),
        "vlp.intrinsics.width_px",
        "1..8192",
    ),
    (
        REAL + CAMERA + INTRINSICS.replace("height_px = 600", "height_px = 100000000"),
        "vlp.intrinsics.height_px",
        "1..8192",
    ),
    (
        REAL + CAMERA + INTRINSICS + "sensor_width_px = 8193\nsensor_height_px = 600\n",
        "vlp.rolling_shutter.sensor_width_px",
        "0..8192",
    ),
    (
        REAL + CAMERA + "[vlp]\n" + TOO_MANY_LEDS + INTRINSICS,
        "vlp.leds",
        "4097 LEDs, more than the limit of 4096",
    ),
    (_option("laser", "queue_size = 0"), "laser.queue_size", "1..4096"),
    (_option("laser", "queue_size = 4097"), "laser.queue_size", "1..4096"),
    (_option("laser", "time_sync_samples = 9223372036854775807"), "laser.time_sync_samples", "1..100"),
    (_option("laser", "cluster = 100"), "laser.cluster", "1..99"),
    (_option("laser", "first_step = 10000"), "laser.first_step", "0..9999"),
    (_option("laser", "last_step = 10000"), "laser.last_step", "0..9999"),
    (_option("servos", "retries = 101"), "servos.retries", "0..100"),
    (_option("rfid", "queue_size = 100000000"), "rfid.queue_size", "1..4096"),
    (_option("rfid", f"antenna_ports = {list(range(1, 17))}"), "rfid.antenna_ports", "16 entries"),
    (_option("camera", "device_index = 256"), "camera.device_index", "0..255"),
    (sim_config("[camera]\ntruth_history = 100000000\n"), "camera.truth_history", "1..4096"),
    (REAL + "[record]\nmax_mb = 1e7\n", "record.max_mb", "at most 1000000"),
]


@pytest.mark.parametrize(
    ("text", "key", "words"), OVER_THE_LIMIT, ids=[f"{k}:{w}" for _, k, w in OVER_THE_LIMIT]
)
def test_a_count_or_size_over_its_limit_names_the_key(
    tmp_path: Path, text: str, key: str, words: str
) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert (info.value.key, info.value.file) == (key, str(path)), str(info.value)
    assert words in str(info.value)


def test_counts_and_sizes_at_their_limits_load(tmp_path: Path) -> None:
    config = parse_config(
        REAL
        + CAMERA
        + "width = 8192\nheight = 8192\n"
        + "[vlp]\n"
        + ONE_LED.format(table="vlp.leds", i=0)
        + INTRINSICS.replace("width_px = 800", "width_px = 8192")
        + "sensor_width_px = 8192\nsensor_height_px = 8192\n"
        + '[laser]\nbackend = "urg"\nurl = "/dev/urg"\nqueue_size = 4096\ncluster = 99\n'
        + "time_sync_samples = 100\nfirst_step = 0\nlast_step = 9999\n[record]\nmax_mb = 1000000\n"
    )
    assert config.devices[DeviceKind.LASER].options["queue_size"] == 4096
    assert config.vlp.intrinsics is not None and config.vlp.intrinsics.sensor_width_px == 8192


def test_an_led_map_file_over_the_limit_names_the_map(tmp_path: Path) -> None:
    leds = write(tmp_path, "".join(ONE_LED.format(table="leds", i=i) for i in range(4097)), "leds.toml")
    path = write(tmp_path, REAL + CAMERA + '[vlp]\nled_map = "leds.toml"\n' + INTRINSICS)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert (info.value.key, info.value.file) == ("leds", str(leds))
    assert "more than the limit of 4096" in info.value.reason


@pytest.mark.parametrize(
    ("field", "bad", "words"),
    [
        ("image_width: 640", "image_width: 100000", "image_width must be an integer 1..8192"),
        ("[500.0, 0, 319.5", "[500.0, 0, .nan", "camera_matrix.data[2] must be finite"),
        ("[0.01, -0.02, 0, 0, 0]", "[0.01, .inf, 0, 0, 0]", "distortion_coefficients.data[1] must be finite"),
    ],
    ids=["size", "nan", "inf"],
)
def test_a_camera_info_over_the_limit_or_not_finite(tmp_path: Path, field: str, bad: str, words: str) -> None:
    info = (
        "image_width: 640\nimage_height: 480\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
        "  data: [500.0, 0, 319.5, 0, 501.0, 239.5, 0, 0, 1]\ndistortion_model: plumb_bob\n"
        "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0.01, -0.02, 0, 0, 0]\n"
    )
    assert field in info
    write(tmp_path, info.replace(field, bad), "camera_info.yaml")
    path = write(tmp_path, REAL + CAMERA + '[vlp]\ncamera_info = "camera_info.yaml"\n')
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert err.value.key == "vlp.camera_info" and words in err.value.reason, str(err.value)
