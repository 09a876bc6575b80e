"""The config file's [exploration] table: defaults, the explorer by name, mistakes that name the key."""

from __future__ import annotations

import pytest

from agent.config import parse_config
from agent.exploration import ExploreConfig, ExplorerKind
from drivers.errors import ConfigError

BASE = 'output.url = "/dev/ttyS0"\n[servos]\nbackend = "dynamixel"\nport = "/dev/ttyUSB0"\n'


def test_without_the_table_the_defaults_apply() -> None:
    assert parse_config(BASE).exploration == ExploreConfig()


def test_the_sp2atm_explorer_and_its_keys_are_read() -> None:
    config = parse_config(
        BASE + '[exploration]\nexplorer = "sp2atm"\nmerge_m = 0.5\nast_beams = 90\nlocality_m = 0\n'
        "door_width_m = 1.0\n"
    ).exploration
    assert config.explorer is ExplorerKind.SP2ATM
    assert (config.merge_m, config.ast_beams, config.locality_m, config.door_width_m) == (0.5, 90, 0.0, 1.0)


def test_keys_are_read() -> None:
    config = parse_config(
        BASE + '[exploration]\nexplorer = "frontier"\nmin_frontier_size_m = 0.5\nmax_failures = 2\n'
        "return_home = true\ngain_scale = 0\n"
    ).exploration
    assert config.explorer is ExplorerKind.FRONTIER
    assert config.min_frontier_size_m == 0.5 and config.max_failures == 2
    assert config.return_home and config.gain_scale == 0.0


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ('explorer = "sp2atm2"', "exploration.explorer"),
        ("ast_beams = 4", "exploration.ast_beams"),
        ("locality_m = -1", "exploration.locality_m"),
        ("min_frontier_size_m = 0", "exploration.min_frontier_size_m"),
        ("max_failures = 0", "exploration.max_failures"),
        ("gain_scale = -1", "exploration.gain_scale"),
        ("return_home = 1", "exploration.return_home"),
        ("blacklist_radius = 0.5", "exploration.blacklist_radius"),
    ],
)
def test_mistakes_name_the_key(text: str, key: str) -> None:
    with pytest.raises(ConfigError) as caught:
        parse_config(BASE + "[exploration]\n" + text + "\n", "robot.toml")
    assert caught.value.key == key


def test_named_places_are_read_and_a_broken_one_is_refused_naming_the_key() -> None:
    from agent.exploration.config import NamedPoint

    text = (
        BASE + '[exploration]\n[[exploration.places]]\nname = "kitchen"\nx_m = 2.0\ny_m = 3.5\nyaw_deg = 90\n'
        '[[exploration.places]]\nname = "lab"\nx_m = -1\ny_m = 0.5\n'
    )
    places = parse_config(text).exploration.places
    assert places[1] == NamedPoint("lab", -1.0, 0.5, None)
    assert places[0].name == "kitchen" and places[0].yaw_rad == pytest.approx(1.5707963)
    with pytest.raises(ConfigError, match=r"places.*y_m"):
        parse_config(BASE + '[[exploration.places]]\nname = "a"\nx_m = 1\n')
    with pytest.raises(ConfigError, match="names two places"):
        parse_config(BASE + '[[exploration.places]]\nname = "a"\nx_m = 1\ny_m = 1\n' * 2)
    with pytest.raises(ConfigError, match="16 bytes"):
        parse_config(BASE + '[[exploration.places]]\nname = "a-very-long-room-name"\nx_m = 1\ny_m = 1\n')
