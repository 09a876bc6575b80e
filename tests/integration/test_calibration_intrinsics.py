"""`vlp-agent calibrate intrinsics --sim --json`: noisy views of a chessboard rendered through the simulated
camera (nearest-neighbour resize included) give the simulated camera's truth back, and the file written is
camera_info YAML that ROS tools and the agent's config both read."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from agent.config import read_camera_info
from calibration.camera_info import parse_camera_info, parse_simple_yaml
from tests.strict_json import strict_loads

REPO = Path(__file__).resolve().parents[2]


def calibrate(tmp_path: Path, *extra: str) -> dict[str, object]:
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
            *extra,
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
    result: dict[str, object] = strict_loads(out.stdout)
    return result


def test_intrinsics_from_rendered_views_meet_the_acceptance_figures(tmp_path: Path) -> None:
    r = calibrate(tmp_path, "--views", "25")
    assert r["ok"] and r["views"] == 25
    for key in ("rms_px", "views", "fx", "fy", "cx", "cy", "fx_error_pct", "principal_point_error_px"):
        assert key in r, key
    assert r["rms_px"] <= 0.3
    assert r["fx_error_pct"] <= 0.5
    assert r["principal_point_error_px"] <= 1.0
    text = (tmp_path / "camera_info.yaml").read_text()
    data = parse_simple_yaml(text)
    assert data["camera_matrix"]["rows"] == 3 and len(data["camera_matrix"]["data"]) == 9
    assert data["projection_matrix"]["cols"] == 4 and len(data["projection_matrix"]["data"]) == 12
    info = parse_camera_info(text)
    assert (info.width, info.height) == (800, 600)
    assert info.fx == pytest.approx(r["fx"], abs=1e-3)
    agent_view = read_camera_info(tmp_path / "camera_info.yaml", "vlp.camera_info", "robot.toml")
    assert agent_view.cx_px == pytest.approx(r["cx"], abs=1e-3)
    figure = cv2.imread(str(tmp_path / "camera_info.png"))
    assert figure is not None and figure.shape[0] > 300
