"""``vlp-agent calibrate forward-camera``: on the simulated robot (a board drawn in front of the forward
camera, over its room) the step finds the forward camera's true focal length and principal point; the file it
writes is what ``[camera.forward] camera_info`` reads into the follow loop's view (distortion included); bad
input (no board, too few views, no forward camera, no robot) is a CalibrationError saying what to do."""

from __future__ import annotations

import argparse
import math
import signal
from pathlib import Path

import numpy as np
import pytest

from agent.cli import main
from agent.config import parse_config
from agent.runtime.follow_loop import CameraView
from agent.runtime.follow_setup import forward_view
from agent.shipped import WORLDS
from calibration import forward_camera
from calibration.boards import BoardDetector, BoardSpec
from calibration.context import SimOptions, StepContext
from calibration.files import commit
from calibration.report import CalibrationError
from calibration.sim import BoardHelper, forward_target_renderer
from drivers.errors import ConfigError
from drivers.sim.worldfile import load_world
from tests.helpers import REAL_ROBOT

# The simulated forward camera: small frames (a fast test), a 62 degree lens, the principal point off centre.
WIDTH, HEIGHT, HFOV_DEG, CX, CY = 320, 240, 62.0, 166.5, 115.75


class QuietConsole:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def say(self, text: str = "") -> None:
        self.lines.append(text)

    def status(self, text: str) -> None:
        pass

    def ask(self, question: str) -> str:
        raise EOFError


def options(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    parser.add_argument("--output", default=None)
    forward_camera.add_arguments(parser)
    return parser.parse_args(list(argv))


def sim_world(tmp_path: Path) -> Path:
    path = tmp_path / "world.toml"
    path.write_text(
        (WORLDS / "env1.toml").read_text()
        + f"\n[forward_camera]\nwidth_px = {WIDTH}\nheight_px = {HEIGHT}\nhfov_deg = {HFOV_DEG}\n"
        f"cx_px = {CX}\ncy_px = {CY}\n"
    )
    return path


def robot_config(tmp_path: Path, forward: str) -> Path:
    path = tmp_path / "robot.toml"
    path.write_text(REAL_ROBOT + forward)
    return path


def test_the_simulated_forward_camera_is_recovered_and_its_file_reaches_the_follow_loop(
    tmp_path: Path,
) -> None:
    ctx = StepContext(QuietConsole(), tmp_path / "cal", SimOptions(sim_world(tmp_path), 0))
    result = forward_camera.run(ctx, options("--views", "8", "--min-views", "6"))
    v = result.values
    f_true = (WIDTH / 2.0) / math.tan(math.radians(HFOV_DEG) / 2.0)
    assert v["truth"] == {"fx": round(f_true, 3), "fy": round(f_true, 3), "cx": CX, "cy": CY}
    # Within 0.5 % in focal length and 1.5 px in principal point (measured: 0.08 %, 0.52 px).
    assert abs(v["fx"] - f_true) / f_true < 0.005 and abs(v["fy"] - f_true) / f_true < 0.005
    assert math.hypot(v["cx"] - CX, v["cy"] - CY) < 1.5
    assert v["rms_px"] < 0.3 and v["views"] == 8 and v["cells_covered"] >= 7
    assert result.ok, result.text()

    commit(result)
    info = tmp_path / "cal" / "forward_camera_info.yaml"
    assert info.is_file() and info.with_suffix(".png").is_file()
    image = tmp_path / "frame.npy"
    np.save(image, np.zeros((HEIGHT, WIDTH, 3), dtype=np.uint8))
    config = parse_config(
        REAL_ROBOT + f'[camera.forward]\nbackend = "fake"\nimage = "{image}"\ncamera_info = "{info}"\n'
        "[camera.forward.mount]\nz_m = 1.1\n"
    )
    assert config.forward_view is not None
    view = forward_view(config.forward_view)
    assert (view.width_px, view.height_px) == (WIDTH, HEIGHT)
    assert view.f_px == pytest.approx(v["fx"], abs=1e-3) and view.fv_px == pytest.approx(v["fy"], abs=1e-3)
    assert (view.cx_px, view.cy_px) == pytest.approx((v["cx"], v["cy"]), abs=1e-3)
    assert view.distortion == pytest.approx(tuple(v["distortion"]), abs=1e-6)
    assert view.mount[2] == 1.1


def test_the_follow_loop_view_applies_the_calibrated_distortion() -> None:
    """A barrel lens (k1 < 0): a point off axis is imaged nearer the centre than the pinhole puts it, and the
    bearing of that pixel is the point's true bearing again."""
    pinhole = CameraView(640, 480, math.radians(70.0), 320.0, 240.0, (0.1, 0.0, 1.3, 0.0))
    lens = CameraView(
        640,
        480,
        math.radians(70.0),
        320.0,
        240.0,
        (0.1, 0.0, 1.3, 0.0),
        None,
        0.1,
        (-0.3, 0.1, 0.001, -0.002, 0.0),
    )
    for forward_m, left_m, height_m in ((2.0, 1.0, 1.6), (3.0, -1.5, 0.8), (1.5, 0.2, 1.3)):
        u0, _ = pinhole.project(forward_m, left_m, height_m) or (0.0, 0.0)
        uv = lens.project(forward_m, left_m, height_m)
        assert uv is not None
        assert abs(uv[0] - 320.0) < abs(u0 - 320.0)
        # Exactly: the bearing of the ray through the pixel, undistorted.
        back = lens.bearing(*uv)
        z = height_m - 1.3
        depth = math.cos(0.1) * forward_m + math.sin(0.1) * z
        up = -math.sin(0.1) * forward_m + math.cos(0.1) * z
        fwd = math.cos(0.1) - math.sin(0.1) * (up / depth)
        assert back == pytest.approx(math.atan2(left_m / depth, fwd), abs=1e-9)
    assert lens.scaled(320, 240).distortion == lens.distortion


def test_no_board_in_the_forward_camera_s_frames(tmp_path: Path) -> None:
    image = tmp_path / "wall.npy"
    np.save(image, np.full((120, 160, 3), 180, dtype=np.uint8))
    config = robot_config(tmp_path, f'[camera.forward]\nbackend = "fake"\nimage = "{image}"\n')
    ctx = StepContext(QuietConsole(), tmp_path / "cal", None, config)
    with pytest.raises(CalibrationError, match=r"no board found in any of the [1-9][0-9]* images"):
        forward_camera.run(ctx, options("--views", "3", "--min-views", "3", "--timeout-s", "0.5"))
    assert not (tmp_path / "cal").exists()


def test_a_board_held_in_one_place_gives_too_few_views(tmp_path: Path) -> None:
    """The fake camera repeats one frame with the board in it: one view, every later frame too like it."""
    world = load_world(sim_world(tmp_path))
    detector = BoardDetector(BoardSpec("chessboard", 9, 6, 0.03, 0.0, "DICT_4X4_50"), equalize_first=False)
    renderer = forward_target_renderer(world, detector.target, seed=3)
    rot, t = BoardHelper(renderer, seed=3).pose((1, 1), False, True)
    frame = renderer.render(rot, t).image
    assert detector.detect(frame) is not None
    image = tmp_path / "board.npy"
    np.save(image, frame)
    config = robot_config(
        tmp_path, f'[camera.forward]\nbackend = "fake"\nimage = "{image}"\nframe_rate_hz = 10\n'
    )
    ctx = StepContext(QuietConsole(), tmp_path / "cal", None, config)
    with pytest.raises(
        CalibrationError, match=r"too few views: 1 usable, at least 3 needed .*too like view 1"
    ):
        forward_camera.run(ctx, options("--views", "3", "--min-views", "3", "--timeout-s", "0.6"))


def test_a_robot_without_a_forward_camera_or_without_a_robot(tmp_path: Path) -> None:
    ctx = StepContext(QuietConsole(), tmp_path, None, robot_config(tmp_path, ""))
    with pytest.raises(CalibrationError, match=r"no forward camera: its config has no \[camera.forward\]"):
        forward_camera.run(ctx, options())
    with pytest.raises(CalibrationError, match="needs the robot: pass --config FILE"):
        forward_camera.run(StepContext(QuietConsole(), tmp_path), options())
    with pytest.raises(CalibrationError, match=r"--views .* must be at least --min-views"):
        forward_camera.run(ctx, options("--views", "2", "--min-views", "3"))


def test_the_cli_step_refuses_clearly_without_the_camera(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = robot_config(tmp_path, "")
    sigterm = signal.getsignal(signal.SIGTERM)  # the command installs its own
    try:
        code = main(
            ["calibrate", "forward-camera", "--config", str(config), "--json", "--dir", str(tmp_path)]
        )
    finally:
        signal.signal(signal.SIGTERM, sigterm)
    out = capsys.readouterr()
    assert code == 1, out.err
    assert "vlp-agent calibrate forward-camera: the robot has no forward camera" in out.err
    assert out.out == ""


@pytest.mark.parametrize(
    ("table", "key", "words"),
    [
        ('camera_info = "{info}"\nhfov_deg = 60.0\n', "camera.forward.hfov_deg", "not both"),
        ('camera_info = "nowhere.yaml"\n', "camera.forward.camera_info", "cannot read"),
    ],
)
def test_camera_info_key_errors(tmp_path: Path, table: str, key: str, words: str) -> None:
    info = tmp_path / "forward_camera_info.yaml"
    info.write_text(
        "image_width: 320\nimage_height: 240\ncamera_name: forward_camera\n"
        "camera_matrix: {rows: 3, cols: 3, data: [266, 0, 160, 0, 266, 120, 0, 0, 1]}\n"
    )
    image = tmp_path / "frame.npy"
    np.save(image, np.zeros((240, 320, 3), dtype=np.uint8))
    text = REAL_ROBOT + f'[camera.forward]\nbackend = "fake"\nimage = "{image}"\n' + table.format(info=info)
    with pytest.raises(ConfigError) as caught:
        parse_config(text, str(tmp_path / "robot.toml"))
    assert caught.value.key == key and words in str(caught.value)
