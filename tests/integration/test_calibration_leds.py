"""`vlp-agent calibrate leds` on the simulated robot: it drives under each LED, reads its signature with the
VLP decoder, and writes the LED map; in a world where two LEDs blink almost alike it says so and does not save
the map (the report PNG is saved)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2

from agent import figure
from tests.figures import has_swatch
from tests.strict_json import strict_loads

REPO = Path(__file__).resolve().parents[2]
ENV1 = REPO / "examples" / "worlds" / "env1.toml"
COORDINATES = (
    "id,x_m,y_m,z_m\nL1,-0.465,0.495,1.5\nL2,-0.460,-0.420,1.5\nL3,0.460,0.490,1.5\nL4,0.480,-0.425,1.5\n"
)


def test_led_survey_measures_signatures_and_warns_about_look_alikes(tmp_path: Path) -> None:
    # env1 with L3 re-fitted with a driver blinking almost like L1's (1500 Hz, duty 0.3).
    text = ENV1.read_text()
    text = text.replace(
        'id = "L3"\nx_m = 0.460\ny_m = 0.490\nfrequency_hz = 3500.0\nduty = 0.4',
        'id = "L3"\nx_m = 0.460\ny_m = 0.490\nfrequency_hz = 1580.0\nduty = 0.33',
    )
    assert "1580.0" in text
    world = tmp_path / "lookalike.toml"
    world.write_text(text)
    csv = tmp_path / "leds.csv"
    csv.write_text(COORDINATES)
    out_dir = tmp_path / "out"
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "agent.cli",
            "calibrate",
            "leds",
            "--world",
            str(world),
            "--json",
            "--dir",
            str(out_dir),
            "--coordinates",
            str(csv),
            "--frames",
            "8",
        ],
        capture_output=True,
        stdin=subprocess.DEVNULL,  # nobody to answer: a step on --sim asks nothing
        text=True,
        timeout=240,
        cwd=REPO,
        check=False,
    )
    assert out.returncode == 3, out.stderr  # done, but the checks failed
    assert "Traceback" not in out.stderr, out.stderr[-3000:]
    r = strict_loads(out.stdout)
    assert r["warnings"] and "L1 and L3 are too close to tell apart" in r["warnings"][0]
    by_id = {led["id"]: led for led in r["leds"]}
    truth = {"L1": (1500.0, 0.3), "L2": (2500.0, 0.6), "L3": (1580.0, 0.33), "L4": (4500.0, 0.5)}
    for led_id, (f, d) in truth.items():
        assert abs(by_id[led_id]["frequency_hz"] / f - 1) < 0.02, (led_id, by_id[led_id])
        assert abs(by_id[led_id]["duty"] - d) < 0.06, (led_id, by_id[led_id])
    assert r["frequency_error_pct_max"] < 2.0
    # The map that would mislead the pipeline is held back; the report is there.
    assert not (out_dir / "leds.toml").exists()
    assert r["not_saved"] == [str(out_dir / "leds.toml")]
    # The report's picture: the LED map and the signatures with ticks, each LED named, a legend.
    picture = cv2.imread(str(out_dir / "leds.png"))
    assert picture is not None and picture.shape[1] >= 800
    assert has_swatch(picture, figure.LED)
