"""Following on the real agent's path (agent.runtime.follow_setup, ``vlp-agent run --follow``):
``[camera.forward]``'s mount and lens keys reach the follow loop's view of the camera, the fake forward
camera backend feeds it frames, and a malformed table is a ConfigError naming its key."""

from __future__ import annotations

import json
import math
import types
from pathlib import Path

import numpy as np
import pytest

from agent.config import parse_config
from agent.runtime.devices import build_forward_camera
from agent.runtime.follow_loop import CameraView
from agent.runtime.follow_setup import forward_view, make_follow_loop
from agent.shipped import WORLDS
from drivers.errors import ConfigError
from tests.helpers import REAL_ROBOT
from tests.unit.test_follow_loop import make_scan

LASER = '[laser]\nbackend = "urg"\nurl = "/dev/urg"\n'


def _image(tmp_path: Path, width: int = 320, height: int = 240) -> Path:
    rng = np.random.default_rng(1)
    path = tmp_path / "forward.npy"
    np.save(path, rng.integers(0, 255, (height, width, 3), dtype=np.uint8))
    return path


def _config(tmp_path: Path, forward: str) -> str:
    return (
        REAL_ROBOT + LASER + f'[camera.forward]\nbackend = "fake"\nimage = "{_image(tmp_path)}"\n' + forward
    )


def test_the_mount_and_lens_keys_reach_the_follow_loop(tmp_path: Path) -> None:
    """The keys become the loop's CameraView; the fake camera's frames go through the fine layer with that
    view: the person, straight ahead of the robot, is where the yawed, raised, tilted camera sees them."""
    config = parse_config(
        _config(
            tmp_path,
            "width = 320\nheight = 240\nhfov_deg = 60.0\ncx_px = 150.0\ncy_px = 130.0\n"
            "[camera.forward.mount]\nx_m = 0.3\ny_m = 0.1\nz_m = 1.1\nyaw_deg = 20.0\npitch_deg = 10.0\n",
        )
    )
    assert config.forward_view is not None
    view = forward_view(config.forward_view)
    assert view.mount == pytest.approx((0.3, 0.1, 1.1, math.radians(20.0)))
    assert view.pitch_rad == pytest.approx(math.radians(10.0))
    assert view.hfov_rad == pytest.approx(math.radians(60.0))
    assert (view.width_px, view.height_px, view.cx_px, view.cy_px) == (320, 240, 150.0, 130.0)

    # The agent's follow path on fakes: the robot stands at (1, 3) facing +x, the person 2.5 m ahead.
    sent: list[tuple[float, float]] = []
    now = [0.0]
    estimate = types.SimpleNamespace(x_m=1.0, y_m=3.0, yaw_rad=0.0)
    agent = types.SimpleNamespace(
        pose=lambda: (estimate, 0xFF),
        flags=lambda: 0xFF,
        fusion=types.SimpleNamespace(estimate_at=lambda t_ns: estimate, reset_counter=0),
        coarse=None,
        command_velocity=lambda v, w: sent.append((v, w)),
        clock_ns=lambda: int(now[0] * 1e9),
        navigation=None,
        scan_listeners=[],
    )
    loop = make_follow_loop(agent, config, (0.0, 0.0, 0.0), view)
    assert agent.scan_listeners == [loop.on_scan]
    camera = build_forward_camera(config.forward_camera, config.file)  # type: ignore[arg-type]
    camera.open()
    try:
        frame = camera.grab(1.0)
        assert frame.image.shape == (240, 320, 3)
        loop.on_scan(make_scan(0.0, (3.7, 3.0), 0))
        assert loop.tracker.tracking
        frame = type(frame)(frame.image, frame.sequence, 0)
        loop.on_frame(frame)
    finally:
        camera.close()
    # The loop looked for the person where the mount puts them: range and bearing from the camera.
    assert loop.locator is not None and loop.locator.target is not None
    person = loop.tracker.estimate()
    assert person is not None
    cam_x, cam_y = 1.0 + 0.3, 3.0 + 0.1
    rng, bearing = loop.locator.target
    assert rng == pytest.approx(math.hypot(person.xy[0] - cam_x, person.xy[1] - cam_y), abs=1e-6)
    expected = math.atan2(person.xy[1] - cam_y, person.xy[0] - cam_x) - math.radians(20.0)
    assert bearing == pytest.approx(expected, abs=1e-6)
    # ... and drew their head and shoulders through the tilted lens: an independent pinhole projection.
    box = view.head_shoulder_box(rng, bearing)
    assert box is not None
    f = 160.0 / math.tan(math.radians(30.0))
    p = math.radians(10.0)
    rows = []
    for side in (-0.225, 0.225):  # the top corners: the head's top, half a shoulder width either side
        forward = rng * math.cos(bearing) - side * math.sin(bearing)
        z = 1.75 - 1.1
        depth = math.cos(p) * forward + math.sin(p) * z
        rows.append(130.0 - f * (-math.sin(p) * forward + math.cos(p) * z) / depth)
    assert box[1] == pytest.approx(min(rows), abs=0.5)
    centre = (box[0] + box[2] / 2.0, box[1] + box[3] / 2.0)
    assert view.bearing(*centre) == pytest.approx(bearing, abs=0.02)


def test_a_column_is_a_bearing_through_the_tilt_and_frames_of_another_size_scale() -> None:
    level = CameraView(640, 480, math.radians(70.0), 319.5, 239.5, (0.0, 0.0, 1.0, 0.0))
    tilted = CameraView(640, 480, math.radians(70.0), 319.5, 239.5, (0.0, 0.0, 1.0, 0.0), None, 0.3)
    for cam in (level, tilted):
        for fwd, left, h in ((2.0, 0.5, 1.6), (3.0, -0.8, 0.5), (1.5, 0.2, 1.9)):
            uv = cam.project(fwd, left, h)
            assert uv is not None
            assert cam.bearing(*uv) == pytest.approx(math.atan2(left, fwd), abs=1e-9)
    half = tilted.scaled(320, 240)
    uv, uv2 = tilted.project(2.0, 0.4, 1.5), half.project(2.0, 0.4, 1.5)
    assert uv is not None and uv2 is not None
    assert uv2 == pytest.approx(((uv[0] + 0.5) / 2 - 0.5, (uv[1] + 0.5) / 2 - 0.5), abs=1e-6)


@pytest.mark.parametrize(
    ("forward", "key", "words"),
    [
        ("mount = 3\n", "camera.forward.mount", "must be a table"),
        ("[camera.forward.mount]\npitch_deg = 60.0\n", "camera.forward.mount.pitch_deg", "within +-45"),
        ("[camera.forward.mount]\nroll_deg = 5.0\n", "camera.forward.mount.roll_deg", ""),
        ("[camera.forward.mount]\nz_m = -1.0\n", "camera.forward.mount.z_m", "0..3 m"),
        ("hfov_deg = 60.0\nfx_px = 500.0\n", "camera.forward.fx_px", "not both"),
        ("hfov_deg = 200.0\n", "camera.forward.hfov_deg", "10..170"),
        ("fy_px = 500.0\n", "camera.forward.fy_px", "needs fx_px"),
        ("fx_px = 500.0\ncx_px = 100.0\n", "camera.forward.cx_px", "width and height"),
        ("width = 320\nheight = 240\nfx_px = 500.0\ncx_px = 400.0\n", "camera.forward.cx_px", "inside"),
        ("hfov_deg = 'wide'\n", "camera.forward.hfov_deg", "must be a number"),
    ],
)
def test_a_malformed_forward_camera_table_names_its_key(
    tmp_path: Path, forward: str, key: str, words: str
) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(_config(tmp_path, forward))
    assert info.value.key == key and words in str(info.value)


def test_the_simulated_camera_takes_its_mount_from_the_world_and_the_image_must_exist(tmp_path: Path) -> None:
    sim = f'[sim]\nworld = "{WORLDS / "follow_straight.toml"}"\n[camera.forward]\n'
    with pytest.raises(ConfigError) as info:
        parse_config(sim + "hfov_deg = 60.0\n")
    assert info.value.key == "camera.forward.hfov_deg" and "world file" in str(info.value)
    with pytest.raises(ConfigError) as info:
        parse_config(REAL_ROBOT + '[camera.forward]\nbackend = "fake"\nimage = "nowhere.png"\n')
    assert info.value.key == "camera.forward.image" and "no such image" in str(info.value)


def test_run_follow_without_the_lens_or_the_laser_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``vlp-agent run --follow`` builds the follow loop before any device starts: a forward camera without
    its lens, or no laser, fails at once with the key or the reason."""
    from agent.cli import main

    config = tmp_path / "robot.toml"
    config.write_text(_config(tmp_path, "[camera.forward.mount]\nyaw_deg = 5.0\n"))
    assert main(["run", "--config", str(config), "--follow", "--seconds", "1"]) == 1
    assert "camera.forward.hfov_deg" in capsys.readouterr().err
    config.write_text(REAL_ROBOT)
    assert main(["run", "--config", str(config), "--follow", "--seconds", "1"]) == 2
    assert "needs the laser" in capsys.readouterr().err


def test_the_fake_camera_paces_its_frames_and_stops_on_close(tmp_path: Path) -> None:
    from drivers.camera.fake_forward import FakeForwardCamera
    from drivers.errors import DeviceError, DeviceNotFound

    camera = FakeForwardCamera(str(_image(tmp_path)))
    camera.open()
    frames = [camera.grab(1.0) for _ in range(3)]
    assert [f.sequence for f in frames] == [1, 2, 3]
    assert frames[0].host_time_ns <= frames[1].host_time_ns <= frames[2].host_time_ns
    camera.close()
    with pytest.raises(DeviceError):
        camera.grab(0.1)
    np.save(tmp_path / "grey.npy", np.zeros((4, 4), dtype=np.uint8))
    with pytest.raises(DeviceNotFound):
        FakeForwardCamera(str(tmp_path / "grey.npy")).open()


def test_run_without_follow_runs_and_refuses_follow_commands_with_the_reason(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Without ``--follow`` a robot that cannot follow (a forward camera without its lens) still runs; its
    follow commands would be refused FOLLOW_UNAVAILABLE, and the final status says why."""
    from agent.cli import main

    config = tmp_path / "robot.toml"
    config.write_text(_config(tmp_path, "[camera.forward.mount]\nyaw_deg = 5.0\n"))
    assert main(["run", "--config", str(config), "--seconds", "0.5", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    control = summary["follow_control"]
    assert control["set_up"] is False and "camera.forward.hfov_deg" in control["unavailable"]
    assert summary["follow"] is None
