"""The LED survey's pure parts: reading coordinates, telling signatures apart, the LED map it writes (read
back by the robot config's reader), and the VLP-error step's known points."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from agent.config import read_led_map
from agent.vlp.model import LedMap, MapLed
from calibration.leds import LedEntry, Measured, close_pairs, format_led_map, read_coordinates
from calibration.report import CalibrationError
from calibration.vlp_error import grid_points, read_points


def measured(led_id: str, f: float, d: float, sf: float = 5.0, sd: float = 0.005) -> Measured:
    return Measured(LedEntry(led_id, 0.0, 0.0, 1.5), f, d, sf, sd, 10, 10)


def test_read_coordinates(tmp_path: Path) -> None:
    path = tmp_path / "leds.csv"
    path.write_text("id, x_m, y_m, z_m, diameter_m\nL1,-0.465,0.495,1.5,0.1\n\nL2,-0.46,-0.42,1.52,0.086\n")
    entries = read_coordinates(path)
    assert entries == [LedEntry("L1", -0.465, 0.495, 1.5, 0.1), LedEntry("L2", -0.46, -0.42, 1.52, 0.086)]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("id,x_m,y_m\nL1,1,2\n", "line 1: the header needs id, x_m, y_m, z_m (missing z_m)"),
        ("id,x_m,y_m,z_m\nL1,1,2\n", "line 2: 3 fields, the header has 4"),
        ("id,x_m,y_m,z_m\nL1,1,2,1.5\nL2,one,2,1.5\n", "line 3: x_m 'one' is not a number"),
        ("id,x_m,y_m,z_m\nL1,1,2,nan\n", "line 2: z_m must be finite"),
        ("id,x_m,y_m,z_m\n,1,2,1.5\n", "line 2: the id is empty"),
        ("id,x_m,y_m,z_m\n", "lists no LEDs"),
    ],
)
def test_coordinate_mistakes_are_named(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "leds.csv"
    path.write_text(text)
    with pytest.raises(
        CalibrationError,
        match="leds.csv " + message.split(" ", 1)[0] if message.startswith("line") else message,
    ):
        read_coordinates(path)
    with pytest.raises(CalibrationError) as info:
        read_coordinates(path)
    assert message in str(info.value)


def test_close_signatures_are_reported() -> None:
    leds = [measured("L1", 1500, 0.30), measured("L2", 2500, 0.60), measured("L3", 1560, 0.33)]
    pairs = close_pairs(leds)
    assert [(a.entry.id, b.entry.id) for a, b, _ in pairs] == [("L1", "L3")]
    assert "L1 and L3 are too close to tell apart (60 Hz, 0.03 duty apart)" in pairs[0][2]
    # Apart in duty is enough.
    assert close_pairs([measured("L1", 1500, 0.30), measured("L3", 1560, 0.55)]) == []
    # A noisy measurement widens what counts as too close.
    noisy = [measured("L1", 1500, 0.30, sf=80.0), measured("L2", 1900, 0.32, sf=60.0)]
    assert len(close_pairs(noisy)) == 1


def test_one_id_with_two_signatures_is_reported() -> None:
    pairs = close_pairs([measured("A", 1500, 0.3), measured("A", 3000, 0.5), measured("A", 1510, 0.3)])
    texts = [t for _, _, t in pairs]
    assert len(texts) == 2 and all("measured with two signatures" in t for t in texts)


def test_led_map_file_reads_back_in_the_config_and_the_pipeline(tmp_path: Path) -> None:
    leds = [
        Measured(LedEntry("L1", -0.465, 0.495, 1.5), 1509.26, 0.2631, 10.0, 0.03, 10, 10),
        Measured(LedEntry("L2", -0.46, -0.42, 1.5, 0.1), 2487.9, 0.6022, 44.0, 0.009, 9, 10),
    ]
    path = tmp_path / "leds.toml"
    path.write_text(format_led_map(leds, ["test"]))
    loaded = read_led_map(path, "vlp.led_map", "robot.toml")
    assert [(e.id, e.x_m, e.frequency_hz, e.duty, e.diameter_m) for e in loaded] == [
        ("L1", -0.465, 1509.3, 0.263, 0.086),
        ("L2", -0.46, 2487.9, 0.602, 0.1),
    ]
    LedMap(tuple(MapLed(e.id, e.x_m, e.y_m, e.z_m, e.frequency_hz, e.duty, e.diameter_m) for e in loaded))


def test_a_stated_survey_sigma_goes_from_the_csv_to_the_map(tmp_path: Path) -> None:
    """``survey_sigma_m`` (optional column, an empty cell: none) is written to the LED map, which the
    config reads and the pipeline weighs each LED by."""
    csv_path = tmp_path / "leds.csv"
    csv_path.write_text("id,x_m,y_m,z_m,survey_sigma_m\nL1,-0.465,0.495,1.5,0.025\nL2,-0.46,-0.42,1.5,\n")
    entries = read_coordinates(csv_path)
    assert [e.survey_sigma_m for e in entries] == [0.025, None]
    path = tmp_path / "leds.toml"
    path.write_text(
        format_led_map(
            [Measured(e, 1500.0 + 1000 * k, 0.4, 5.0, 0.01, 10, 10) for k, e in enumerate(entries)], []
        )
    )
    loaded = read_led_map(path, "vlp.led_map", "robot.toml")
    assert [e.survey_sigma_m for e in loaded] == [0.025, None]
    csv_path.write_text("id,x_m,y_m,z_m,survey_sigma_m\nL1,-0.465,0.495,1.5,-0.1\n")
    with pytest.raises(CalibrationError, match="line 2: survey_sigma_m must be in"):
        read_coordinates(csv_path)


def test_known_points(tmp_path: Path) -> None:
    path = tmp_path / "points.csv"
    path.write_text("x_m,y_m\n0,0\n0.3,0.1\n-0.2,0.25\n")
    assert read_points(path) == [(0.0, 0.0), (0.3, 0.1), (-0.2, 0.25)]
    path.write_text("x_m,y_m\n0,0\n0.3,north\n")
    with pytest.raises(CalibrationError, match=r"line 3: '0\.3,north' is not two numbers"):
        read_points(path)
    path.write_text("x,y\n0,0\n")
    with pytest.raises(CalibrationError, match="header must be x_m,y_m"):
        read_points(path)
    grid = grid_points(
        LedMap((MapLed("A", -0.5, -0.5, 1.5, 1000, 0.5), MapLed("B", 0.5, 0.5, 1.5, 2000, 0.5)))
    )
    assert len(grid) == 9
    assert grid[0] == pytest.approx((-0.5 + 1 / 6, -0.5 + 1 / 6))
    assert np.mean(grid, axis=0) == pytest.approx((0.0, 0.0), abs=1e-12)
    assert all(math.isfinite(v) for p in grid for v in p)
