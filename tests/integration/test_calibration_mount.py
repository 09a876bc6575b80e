"""`vlp-agent calibrate mount` on the simulated robot: the camera's tilt from the IMU on its bracket and
from a level board, its yaw and place on the base from driving and turning under the board."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np

from calibration.camera_info import CameraInfo, format_camera_info
from drivers.sim.render import RollingShutterRenderer
from drivers.sim.worldfile import load_world
from tests.strict_json import strict_loads

REPO = Path(__file__).resolve().parents[2]
ENV1 = REPO / "examples" / "worlds" / "env1.toml"


def test_mount_step_finds_tilt_yaw_and_place(tmp_path: Path) -> None:
    # The camera calibration the intrinsics step would have left: the simulated camera's own.
    intr = RollingShutterRenderer(load_world(ENV1).camera, ()).output_intrinsics
    k = np.array([[intr.fx_px, 0.0, intr.cx_px], [0.0, intr.fy_px, intr.cy_px], [0.0, 0.0, 1.0]])
    (tmp_path / "camera_info.yaml").write_text(
        format_camera_info(CameraInfo.from_matrices(800, 600, k, np.zeros(5)))
    )
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "agent.cli",
            "calibrate",
            "mount",
            "--sim",
            "--json",
            "--dir",
            str(tmp_path),
            "--imu-seconds",
            "1.0",
            "--drive-m",
            "0.15",
            "--seed",
            "1",
        ],
        capture_output=True,
        stdin=subprocess.DEVNULL,  # nobody to answer: a step on --sim asks nothing
        text=True,
        timeout=240,
        cwd=REPO,
        check=False,
    )
    assert out.returncode == 0, out.stderr
    assert "Traceback" not in out.stderr, out.stderr[-3000:]
    r = strict_loads(out.stdout)
    assert r["ok"], r["checks"]
    assert r["tilt_error_deg"] < 0.08
    assert abs(r["truth"]["yaw_deg"]) > 0.9  # the camera is turned on its bracket
    assert r["yaw_error_deg"] < 0.1
    assert r["offset_error_m"] < 0.004
    # Both tilt measurements agree with the truth (0.2, -0.15 deg in env1).
    for key in ("imu_tilt_deg", "target_tilt_deg"):
        assert abs(r[key][0] - r["truth"]["roll_deg"]) < 0.1, key
        assert abs(r[key][1] - r["truth"]["pitch_deg"]) < 0.1, key
    mount = tomllib.loads((tmp_path / "mount.toml").read_text())["vlp"]["mount"]
    assert set(mount) == {"x_m", "y_m", "z_m", "yaw_rad", "roll_rad", "pitch_rad"}
