"""`vlp-agent calibrate row-time` on the simulated robot: in a world whose camera's row time is 3 % longer
than the config's, the step finds the true one from the LEDs' known frequencies, with an uncertainty that
covers it, and writes it for the config."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

from drivers.sim.worldfile import load_world, nominal_camera
from tests.strict_json import strict_loads

REPO = Path(__file__).resolve().parents[2]
ENV1 = REPO / "examples" / "worlds" / "env1.toml"


def test_row_time_3_percent_off_is_found(tmp_path: Path) -> None:
    text = ENV1.read_text().replace("[errors]\n", "[errors]\nt_row_error_fraction = 0.03\n")
    world_file = tmp_path / "env1_row_time.toml"
    world_file.write_text(text)
    world = load_world(world_file)
    stated = nominal_camera(world).t_row_s
    true = world.camera.t_row_s
    assert abs(true / stated - 1.03) < 1e-12
    out_dir = tmp_path / "out"
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "agent.cli",
            "calibrate",
            "row-time",
            "--world",
            str(world_file),
            "--json",
            "--dir",
            str(out_dir),
        ],
        capture_output=True,
        stdin=subprocess.DEVNULL,
        text=True,
        timeout=240,
        cwd=REPO,
        check=False,
    )
    # The step's own default of 30 frames: with 24 its uncertainty, 0.12-0.17 % beside a loaded machine,
    # stood close to the 0.2 % its check allows, and one CI run in many failed a check. On failure the
    # JSON says which check (its "checks").
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    r = strict_loads(out.stdout)
    assert r["ok"] and r["config_t_row_s"] == stated
    assert abs(r["change_pct"] - 3.0) < 0.3
    # Within 0.2 % of the truth, and the stated uncertainty covers the error.
    assert abs(r["error_pct"]) < 0.2
    assert abs(r["t_row_s"] - true) < 4.0 * r["t_row_sigma_s"]
    assert {led["id"] for led in r["leds"]} == {"L1", "L2", "L3", "L4"}
    assert r["warnings"] == []  # Environment 1's signatures, 1 kHz apart
    written = tomllib.loads((out_dir / "row_time.toml").read_text())
    assert abs(written["vlp"]["rolling_shutter"]["t_row_s"] / true - 1.0) < 0.002
    assert (out_dir / "row_time.png").stat().st_size > 1000
