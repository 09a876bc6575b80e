"""`vlp-agent calibrate laser` on the simulated robot built with its laser turned and off its drawn place,
facing a corner of Environment 1: yaw and position come out right; the file holds [slam.laser_mount]."""

from __future__ import annotations

import math
import subprocess
import sys
import tomllib
from pathlib import Path

from tests.strict_json import strict_loads

REPO = Path(__file__).resolve().parents[2]


def test_laser_step_finds_the_laser_mount(tmp_path: Path) -> None:
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "agent.cli",
            "calibrate",
            "laser",
            "--sim",
            "--json",
            "--dir",
            str(tmp_path),
            "--scans",
            "3",
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
    assert abs(truth["yaw_deg"]) > 0.5  # there is a yaw to find
    assert r["yaw_error_deg"] < 0.15
    assert r["offset_error_m"] < 0.005
    mount = tomllib.loads((tmp_path / "laser.toml").read_text())["slam"]["laser_mount"]
    assert abs(math.degrees(mount["yaw_rad"]) - truth["yaw_deg"]) < 0.15
    assert math.hypot(mount["x_m"] - truth["x_m"], mount["y_m"] - truth["y_m"]) < 0.005
