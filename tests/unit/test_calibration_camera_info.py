"""ROS camera_info YAML: what the intrinsics step writes is valid camera_info (structure checked field by
field, read back by our reader, by the agent's config reader and by OpenCV's FileStorage), and the reader
takes the forms other writers use and names the key that is wrong."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from agent.config import read_camera_info
from calibration.camera_info import CameraInfo, format_camera_info, parse_camera_info, parse_simple_yaml
from drivers.errors import ConfigError

K = np.array([[488.5, 0.0, 401.25], [0.0, 488.75, 298.5], [0.0, 0.0, 1.0]])
D = np.array([-0.1203, 0.0311, 0.00042, -0.00017, 0.0])
P = np.array([[480.0, 0.0, 400.0, 0.0], [0.0, 481.0, 299.0, 0.0], [0.0, 0.0, 1.0, 0.0]])

# As ROS's camera_calibration_parsers (yaml-cpp) writes it.
ROS_FILE = """image_width: 1280
image_height: 960
camera_name: mvcam
camera_matrix:
  rows: 3
  cols: 3
  data: [808.78, 0, 628, 0, 809.1, 475.5, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.2, 0.05, 0, 0, 0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [790, 0, 630, 0, 0, 792, 476, 0, 0, 0, 1, 0]
"""

# As PyYAML writes it with block style, wrapped lines and a document marker.
PYYAML_FILE = """---
camera_matrix:
  cols: 3
  data:
  - 500.0
  - 0.0
  - 320.0
  - 0.0
  - 501.0
  - 240.0
  - 0.0
  - 0.0
  - 1.0
  rows: 3
camera_name: 'narrow_stereo'   # quoted, with a comment
distortion_coefficients:
  cols: 5
  data: [0.0, 0.0, 0.0, 0.0, 0.0]
  rows: 1
distortion_model: plumb_bob
image_height: 480
image_width: 640
"""


def written() -> str:
    info = CameraInfo.from_matrices(800, 600, K, D, P, camera_name="vlp_camera")
    return format_camera_info(info, "vlp-agent calibrate intrinsics\n40 views")


def test_written_file_has_the_camera_info_structure() -> None:
    data = parse_simple_yaml(written())
    assert set(data) == {
        "image_width",
        "image_height",
        "camera_name",
        "camera_matrix",
        "distortion_model",
        "distortion_coefficients",
        "rectification_matrix",
        "projection_matrix",
    }
    assert data["image_width"] == 800 and data["image_height"] == 600
    assert data["distortion_model"] == "plumb_bob"
    for key, (rows, cols) in {
        "camera_matrix": (3, 3),
        "distortion_coefficients": (1, 5),
        "rectification_matrix": (3, 3),
        "projection_matrix": (3, 4),
    }.items():
        assert data[key]["rows"] == rows and data[key]["cols"] == cols
        assert len(data[key]["data"]) == rows * cols
    assert data["camera_matrix"]["data"] == pytest.approx(K.ravel().tolist(), abs=0)
    assert data["distortion_coefficients"]["data"] == pytest.approx(D.tolist(), abs=0)
    assert data["projection_matrix"]["data"] == pytest.approx(P.ravel().tolist(), abs=0)
    assert data["rectification_matrix"]["data"] == [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    assert written().startswith("# vlp-agent calibrate intrinsics\n# 40 views\n")


def test_round_trip_is_exact() -> None:
    info = parse_camera_info(written())
    assert np.array_equal(info.k(), K)
    assert np.array_equal(info.d(), D)
    assert info.projection == tuple(P.ravel())
    assert (info.width, info.height, info.camera_name) == (800, 600, "vlp_camera")


def test_the_agents_config_reader_takes_it(tmp_path: Path) -> None:
    path = tmp_path / "camera_info.yaml"
    path.write_text(written())
    intr = read_camera_info(path, "vlp.camera_info", "robot.toml")
    assert (intr.width_px, intr.height_px) == (800, 600)
    assert (intr.fx_px, intr.fy_px, intr.cx_px, intr.cy_px) == (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    assert intr.distortion == tuple(D)


def test_opencv_filestorage_reads_it() -> None:
    storage = cv2.FileStorage("%YAML:1.0\n---\n" + written(), cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    data = storage.getNode("camera_matrix").getNode("data")
    assert [data.at(i).real() for i in range(data.size())] == K.ravel().tolist()
    assert storage.getNode("distortion_model").string() == "plumb_bob"


def test_reads_ros_and_pyyaml_files() -> None:
    ros = parse_camera_info(ROS_FILE)
    assert (ros.width, ros.fx, ros.cy) == (1280, 808.78, 475.5)
    assert ros.projection[0] == 790.0
    py = parse_camera_info(PYYAML_FILE)
    assert (py.width, py.height, py.fx, py.cx) == (640, 480, 500.0, 320.0)
    assert py.camera_name == "narrow_stereo"
    assert py.distortion == (0.0, 0.0, 0.0, 0.0, 0.0)


def test_multiline_flow_sequence() -> None:
    text = ROS_FILE.replace(
        "data: [808.78, 0, 628, 0, 809.1, 475.5, 0, 0, 1]",
        "data: [808.78, 0, 628,\n    0, 809.1, 475.5,\n    0, 0, 1]",
    )
    assert parse_camera_info(text).fy == 809.1


@pytest.mark.parametrize(
    ("edit", "key"),
    [
        (lambda t: t.replace("image_width: 1280\n", ""), "image_width"),
        (lambda t: t.replace("image_height: 960", "image_height: -3"), "image_height"),
        (lambda t: t.replace("data: [808.78, 0, 628", "data: [808.78, 0, x628"), "camera_matrix.data[2]"),
        (
            lambda t: t.replace(
                "  rows: 3\n  cols: 3\n  data: [808.78", "  rows: 2\n  cols: 3\n  data: [808.78"
            ),
            "camera_matrix.rows",
        ),
        (
            lambda t: t.replace("data: [-0.2, 0.05, 0, 0, 0]", "data: [-0.2, 0.05, 0]").replace(
                "cols: 5", "cols: 3"
            ),
            "distortion_coefficients",
        ),
        (lambda t: t.replace("plumb_bob", "fisheye"), "distortion_model"),
        (lambda t: t.replace("0, 0, 1]\ndistortion_model", "0, 1, 1]\ndistortion_model"), "camera_matrix"),
    ],
)
def test_errors_name_the_key(edit: object, key: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_camera_info(edit(ROS_FILE), "cam.yaml")  # type: ignore[operator]
    assert info.value.key == key
    assert "cam.yaml" in str(info.value)


@pytest.mark.parametrize(
    "text",
    [
        "image_width: 800\n  oops: 1\n",
        "a: 1\na: 2\n",
        "image_width\n",
        "\tx: 1\n",
        "key: [1, 2\n",
        "camera_matrix: {rows: 3, cols: 3}\n",
    ],
)
def test_not_yaml_is_a_config_error(text: str) -> None:
    with pytest.raises(ConfigError):
        parse_camera_info(text)
