"""`vlp-agent calibrate intrinsics --board charuco` on the simulated camera (when OpenCV has cv2.aruco)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from drivers.sim.targets import HAS_ARUCO
from tests.strict_json import strict_loads

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.skipif(not HAS_ARUCO, reason="this OpenCV has no cv2.aruco")
def test_charuco_board_calibrates_the_camera(tmp_path: Path) -> None:
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "agent.cli",
            "calibrate",
            "intrinsics",
            "--sim",
            "--json",
            "--dir",
            str(tmp_path),
            "--board",
            "charuco",
            "--views",
            "15",
            "--min-views",
            "10",
        ],
        capture_output=True,
        stdin=subprocess.DEVNULL,  # nobody to answer: a step on --sim asks nothing
        text=True,
        timeout=240,
        cwd=REPO,
        check=False,
    )
    assert out.returncode in (0, 3), out.stderr
    assert "Traceback" not in out.stderr, out.stderr[-3000:]
    r = strict_loads(out.stdout)
    assert "ChArUco" in r["board"]
    assert r["views"] >= 10
    assert r["rms_px"] <= 0.4
    assert r["fx_error_pct"] <= 1.0
    assert r["principal_point_error_px"] <= 2.0
