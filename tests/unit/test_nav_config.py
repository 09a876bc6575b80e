"""The config file's [navigation] table: defaults, values, and mistakes that name the key."""

from __future__ import annotations

import math

import pytest

from agent.config import parse_config
from agent.navigation.config import NavConfig
from drivers.errors import ConfigError

BASE = 'output.url = "/dev/ttyS0"\n[servos]\nbackend = "dynamixel"\nport = "/dev/ttyUSB0"\n'


def test_without_the_table_the_defaults_apply() -> None:
    assert parse_config(BASE).navigation == NavConfig()


def test_keys_are_read_with_degrees_for_angles() -> None:
    config = parse_config(
        BASE + "[navigation]\nmax_speed_mps = 0.15\nyaw_tolerance_deg = 3.0\nmax_recoveries = 2\n"
        "allow_unknown = true\n"
    ).navigation
    assert config.max_speed_mps == 0.15
    assert config.yaw_tolerance_rad == pytest.approx(math.radians(3.0))
    assert config.max_recoveries == 2 and config.allow_unknown


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("max_speed_mps = -0.1", "navigation.max_speed_mps"),
        ("max_speed_mps = 0.5", "navigation.max_speed_mps"),  # faster than the wheels
        ("stop_margin_m = 0.4", "navigation.slow_margin_m"),  # the stop zone beyond the slow zone
        ("inflation_radius_m = 0.1", "navigation.inflation_radius_m"),
        ("max_recoveries = 0", "navigation.max_recoveries"),
        ("allow_unknown = 1", "navigation.allow_unknown"),
        ("max_sped_mps = 0.1", "navigation.max_sped_mps"),
    ],
)
def test_mistakes_name_the_key(text: str, key: str) -> None:
    with pytest.raises(ConfigError) as caught:
        parse_config(BASE + "[navigation]\n" + text + "\n", "robot.toml")
    assert caught.value.key == key
