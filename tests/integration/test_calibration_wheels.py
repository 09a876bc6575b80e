"""`vlp-agent calibrate wheels` on the simulated robot built with a worn tyre and a track off the drawing:
the measured runs bring wheel radius and track to the truth, the file holds the config keys."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

from tests.strict_json import strict_loads

REPO = Path(__file__).resolve().parents[2]


def test_wheels_step_finds_radius_and_track(tmp_path: Path) -> None:
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "agent.cli",
            "calibrate",
            "wheels",
            "--sim",
            "--json",
            "--dir",
            str(tmp_path),
            "--distance-m",
            "0.4",
            "--turns",
            "1",
            "--speed-mps",
            "0.2",
            "--seed",
            "2",
        ],
        capture_output=True,
        stdin=subprocess.DEVNULL,  # nobody to answer: a step on --sim asks nothing
        text=True,
        timeout=180,
        cwd=REPO,
        check=False,
    )
    assert out.returncode == 0, out.stderr
    assert "Traceback" not in out.stderr, out.stderr[-3000:]
    r = strict_loads(out.stdout)
    assert r["ok"], r["checks"]
    truth = r["truth"]
    design_radius_error = abs(r["nominal_wheel_radius_m"] / truth["wheel_radius_m"] - 1) * 100
    design_track_error = abs(r["nominal_track_m"] / truth["track_m"] - 1) * 100
    # The simulated robot really is off its design, and the calibration takes most of it out.
    assert design_radius_error > 0.4 and design_track_error > 0.5
    assert r["wheel_radius_error_pct"] < 0.3 < design_radius_error
    assert r["track_error_pct"] < 0.5 < design_track_error
    keys = tomllib.loads((tmp_path / "wheels.toml").read_text())["servos"]
    assert keys["wheel_radius_m"] == round(r["wheel_radius_m"], 6)
    assert keys["track_m"] == round(r["track_m"], 6)
