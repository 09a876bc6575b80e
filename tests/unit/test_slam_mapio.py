"""Maps on disk (map_server PGM + YAML, atomic, previous version kept) and the accuracy measures."""

from __future__ import annotations

import math
import os
import re
import stat
from pathlib import Path

import numpy as np
import pytest

from agent.slam.mapio import (
    decode_pgm,
    encode_pgm,
    load_map,
    new_file_mode,
    save_map,
    tidy_map_folder,
    write_png,
)
from agent.slam.metrics import (
    absolute_trajectory_error,
    aligned_trajectory_error,
    relative_pose_error,
    rigid_alignment,
    wall_thickness,
)
from agent.slam.pose import compose
from agent.slam.render import (
    FREE_VALUE,
    OCCUPIED_VALUE,
    UNKNOWN_VALUE,
    MapPath,
    OccupancyImage,
    map_picture,
    occupancy_image,
)
from drivers.errors import ConfigError


def sample_image() -> tuple[np.ndarray, object]:
    log_odds = np.zeros((40, 60), dtype=np.float32)
    log_odds[5:35, 10:50] = -2.0  # free room
    log_odds[5, 10:50] = 3.0  # south wall (row 0 = lowest y)
    log_odds[34, 10:50] = 3.0  # north wall
    log_odds[20, 30] = 0.5  # p = 0.62: neither free nor occupied: unknown
    return log_odds, occupancy_image(log_odds, (-1.5, 2.25), 0.05)


def test_occupancy_image_follows_map_saver_values() -> None:
    _log_odds, image = sample_image()
    pixels = image.pixels  # type: ignore[attr-defined]
    assert pixels.shape == (40, 60)
    assert pixels[0, 0] == UNKNOWN_VALUE
    assert pixels[39 - 5, 20] == OCCUPIED_VALUE  # rows flipped: the south wall is near the bottom
    assert pixels[39 - 34, 20] == OCCUPIED_VALUE
    assert pixels[39 - 10, 20] == FREE_VALUE
    assert pixels[39 - 20, 30] == UNKNOWN_VALUE
    occupied = image.occupied_mask()  # type: ignore[attr-defined]
    assert occupied.sum() == 80


def test_round_trip_and_previous_version(tmp_path: Path) -> None:
    _, image = sample_image()
    files = save_map(image, tmp_path / "maps" / "office.yaml", comment="test map")  # type: ignore[arg-type]
    assert files.previous_yaml is None
    assert re.fullmatch(r"office\.\d{8}T\d{12}Z\.pgm", files.image.name)
    text = files.yaml.read_text()
    assert f"image: {files.image.name}\n" in text and "origin: [-1.500000, 2.250000, 0.000000]" in text
    assert files.image.read_bytes().startswith(b"P5\n# test map\n60 40\n255\n")
    loaded = load_map(files.yaml)
    np.testing.assert_array_equal(loaded.pixels, image.pixels)  # type: ignore[attr-defined]
    assert loaded.resolution_m == pytest.approx(0.05)
    assert loaded.origin == pytest.approx((-1.5, 2.25, 0.0))
    # Saving again keeps the first map as office.prev.yaml (naming the first image), loadable on its own.
    log_odds2 = np.full((10, 10), 3.0, dtype=np.float32)
    second = save_map(occupancy_image(log_odds2, (0.0, 0.0), 0.1), files.yaml)
    assert second.previous_yaml == tmp_path / "maps" / "office.prev.yaml"
    previous = load_map(second.previous_yaml)
    np.testing.assert_array_equal(previous.pixels, image.pixels)  # type: ignore[attr-defined]
    assert load_map(files.yaml).pixels.shape == (10, 10)
    # A third save drops the first image: two versions kept, no temporary files left behind.
    third = save_map(occupancy_image(log_odds2, (1.0, 0.0), 0.1), files.yaml)
    assert sorted(p.name for p in (tmp_path / "maps").iterdir()) == sorted(
        [second.image.name, third.image.name, "office.prev.yaml", "office.yaml"]
    )
    assert load_map(third.previous_yaml or files.yaml).origin == pytest.approx((0.0, 0.0, 0.0))


def test_a_map_of_an_older_release_is_kept_then_replaced(tmp_path: Path) -> None:
    # Before versioned images: office.pgm + office.yaml, and office.prev.{pgm,yaml}.
    old = np.full((3, 4), 254, dtype=np.uint8)
    (tmp_path / "office.pgm").write_bytes(encode_pgm(old))
    (tmp_path / "office.yaml").write_text("image: office.pgm\nresolution: 0.1\norigin: [5, 5, 0]\n")
    (tmp_path / "office.prev.pgm").write_bytes(encode_pgm(old))
    (tmp_path / "office.prev.yaml").write_text("image: office.prev.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n")
    _, image = sample_image()
    save_map(image, tmp_path / "office.yaml")  # type: ignore[arg-type]
    assert load_map(tmp_path / "office.prev.yaml").origin == pytest.approx((5.0, 5.0, 0.0))
    assert not (tmp_path / "office.prev.pgm").exists()  # named by nothing any more
    save_map(image, tmp_path / "office.yaml")  # type: ignore[arg-type]
    assert not (tmp_path / "office.pgm").exists()
    assert len(list(tmp_path.glob("office.*.pgm"))) == 2


def two_versions() -> tuple[OccupancyImage, OccupancyImage]:
    """Two maps that differ in both image and origin, so a mixed pair cannot pass for either."""
    first = occupancy_image(np.full((8, 12), -2.0, dtype=np.float32), (-1.0, 2.0, 0.0), 0.05)
    second = occupancy_image(np.full((6, 5), 3.0, dtype=np.float32), (4.0, -3.0, 0.5), 0.05)
    return first, second


def save_killed_before_rename(yaml_file: Path, image: OccupancyImage, renames: int) -> None:
    """Save in a child process that dies (``os._exit``, no clean-up) just before its rename number
    ``renames`` + 1, as a kill would leave the folder."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        done = 0
        real_replace = os.replace

        def replace(src: str, dst: str) -> None:
            nonlocal done
            if done == renames:
                os._exit(0)
            done += 1
            real_replace(src, dst)

        os.replace = replace  # type: ignore[assignment]
        try:
            save_map(image, yaml_file)
        finally:
            os._exit(0)
    os.waitpid(pid, 0)


def image_name(yaml_file: Path) -> str:
    return next(line[7:] for line in yaml_file.read_text().splitlines() if line.startswith("image: "))


def same_map(loaded: OccupancyImage, expected: OccupancyImage) -> bool:
    return loaded.pixels.shape == expected.pixels.shape and loaded.origin == pytest.approx(expected.origin)


@pytest.mark.parametrize("renames", range(5))
def test_a_kill_at_any_step_leaves_the_old_pair_or_the_new_one(tmp_path: Path, renames: int) -> None:
    first, second = two_versions()
    yaml_file = tmp_path / "map.yaml"
    save_map(first, yaml_file)
    save_killed_before_rename(yaml_file, second, renames)
    loaded = load_map(yaml_file)
    assert same_map(loaded, first) or same_map(loaded, second)
    version = first if same_map(loaded, first) else second
    np.testing.assert_array_equal(loaded.pixels, version.pixels)
    # Whatever was left over goes at the next start; the map still loads the same afterwards.
    tidy_map_folder(yaml_file)
    names = {p.name for p in tmp_path.iterdir()}
    assert not [n for n in names if n.endswith(".tmp")]
    named = {image_name(y) for y in tmp_path.glob("*.yaml")}
    assert {n for n in names if n.endswith(".pgm")} == named
    assert same_map(load_map(yaml_file), version)
    if (tmp_path / "map.prev.yaml").exists():
        assert same_map(load_map(tmp_path / "map.prev.yaml"), first)


@pytest.mark.parametrize("renames", range(3))
def test_a_kill_in_a_fresh_folder_leaves_no_map_or_a_whole_one(tmp_path: Path, renames: int) -> None:
    _, second = two_versions()
    yaml_file = tmp_path / "map.yaml"
    save_killed_before_rename(yaml_file, second, renames)
    if yaml_file.exists():
        assert same_map(load_map(yaml_file), second)
    else:
        with pytest.raises(ConfigError):
            load_map(yaml_file)
        # No image under the name a reader would pair with a later map.yaml.
        assert not (tmp_path / "map.pgm").exists()
    tidy_map_folder(yaml_file)
    assert [p.name for p in tmp_path.iterdir() if p.suffix in (".tmp", ".pgm")] == (
        [image_name(yaml_file)] if yaml_file.exists() else []
    )


def test_tidy_removes_only_this_maps_left_overs(tmp_path: Path) -> None:
    first, _ = two_versions()
    files = save_map(first, tmp_path / "map.yaml")
    left = [
        ".map.yaml.k2j4_x9a.tmp",
        ".map.prev.yaml.abcdefgh.tmp",
        ".map.20261126T101500123456Z.pgm.q1w2e3r4.tmp",
        ".map.png.zzzzzzzz.tmp",
        "map.20261126T101500123456Z.pgm",  # an image whose YAML never made it
    ]
    kept = [".mapping.yaml.abcdefgh.tmp", ".other.yaml.abcdefgh.tmp", "map.png", "notes.txt", "office.pgm"]
    for name in left + kept:
        (tmp_path / name).write_bytes(b"x")
    removed = tidy_map_folder(tmp_path / "map.yaml")
    assert sorted(p.name for p in removed) == sorted(left)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([*kept, files.image.name, "map.yaml"])
    assert tidy_map_folder(tmp_path / "absent" / "map.yaml") == []


@pytest.mark.parametrize("umask", [0o022, 0o027])
def test_map_files_get_the_umask_modes(tmp_path: Path, umask: int) -> None:
    first, second = two_versions()
    old = os.umask(umask)
    try:
        save_map(first, tmp_path / "map.yaml")
        files = save_map(second, tmp_path / "map.yaml")
        png = write_png(tmp_path / "map.png", second.pixels)
    finally:
        os.umask(old)
    assert new_file_mode() == 0o666 & ~old
    for path in (files.yaml, files.image, files.previous_yaml, png):
        assert path is not None
        assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~umask, path.name


def test_world_to_pixel_matches_map_server_convention() -> None:
    _, image = sample_image()
    # The lower-left corner of the lower-left cell is the origin; pixel rows count from the top.
    px = image.world_to_pixel(np.array([[-1.5, 2.25], [-1.5 + 0.05 * 60, 2.25 + 0.05 * 40]]))  # type: ignore[attr-defined]
    np.testing.assert_allclose(px, [[0.0, 40.0], [60.0, 0.0]])


def test_pgm_ascii_and_maxval() -> None:
    pixels = decode_pgm(b"P2\n# a comment\n3 2\n15\n0 15 7\n15 0 0\n")
    np.testing.assert_array_equal(pixels, [[0, 255, 119], [255, 0, 0]])
    binary = encode_pgm(np.array([[1, 2], [3, 4]], dtype=np.uint8))
    np.testing.assert_array_equal(decode_pgm(binary), [[1, 2], [3, 4]])


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"P6\n2 2\n255\n" + bytes(12), "not a PGM"),
        (b"P5\n2 2\n255\n" + bytes(3), "truncated: 3 of 4 bytes"),
        (b"P5\n2", "truncated PGM header"),
        (b"P5\n2 2\n65535\n" + bytes(8), "need 8-bit"),
        (b"P5\nx 2\n255\n", "not numbers"),
    ],
)
def test_bad_pgm(data: bytes, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        decode_pgm(data, "map.pgm")


@pytest.mark.parametrize(
    ("yaml", "key"),
    [
        ("resolution: 0.05\norigin: [0, 0, 0]\n", "image"),
        ("image: m.pgm\norigin: [0, 0, 0]\n", "resolution"),
        ("image: m.pgm\nresolution: fast\norigin: [0, 0, 0]\n", "resolution"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0]\n", "origin"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nfree_thresh: 0.9\n", "free_thresh"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nmode: scale\n", "mode"),
        ("image: missing.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n", "image"),
        ("just text\n", "line 1"),
    ],
)
def test_bad_yaml_names_the_key(tmp_path: Path, yaml: str, key: str) -> None:
    (tmp_path / "m.pgm").write_bytes(encode_pgm(np.zeros((2, 2), dtype=np.uint8)))
    (tmp_path / "m.yaml").write_text(yaml)
    with pytest.raises(ConfigError) as err:
        load_map(tmp_path / "m.yaml")
    assert err.value.key == key
    assert err.value.file == str(tmp_path / "m.yaml")


def test_negate_inverts(tmp_path: Path) -> None:
    (tmp_path / "m.pgm").write_bytes(encode_pgm(np.array([[0, 255]], dtype=np.uint8)))
    (tmp_path / "m.yaml").write_text("image: m.pgm\nresolution: 0.1\norigin: [0, 0, 0]\nnegate: 1\n")
    assert load_map(tmp_path / "m.yaml").occupied_mask().tolist() == [[False, True]]


def test_png_of_the_map_picture(tmp_path: Path) -> None:
    _, image = sample_image()
    path = np.array([[-1.0, 2.6], [0.0, 3.0], [1.0, 3.5]])
    picture = map_picture(image, [MapPath("path", path, (0, 0, 255))])  # type: ignore[arg-type]
    assert picture.shape[1] >= 800
    assert (np.all(picture == (0, 0, 255), axis=2)).sum() > 10  # the red path was drawn
    written = write_png(tmp_path / "t.png", picture)
    assert written.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# -- metrics ----------------------------------------------------------------------------------------


def test_relative_pose_error_zero_and_known() -> None:
    rng = np.random.default_rng(0)
    steps = rng.normal(0.0, 0.3, (50, 3))
    reference = np.zeros((51, 3))
    for i, step in enumerate(steps):
        reference[i + 1] = compose(reference[i], step)
    same = relative_pose_error(reference, reference)
    assert same.n == 50 and same.trans_error_m_mean == pytest.approx(0.0, abs=1e-12)
    # The same path in another frame has no relative error either: the metric ignores global placement.
    moved = compose(np.array([3.0, -2.0, 1.0]), reference)
    assert relative_pose_error(reference, moved).trans_error_m_mean == pytest.approx(0.0, abs=1e-9)
    # Every step ends 1 cm off sideways: E = D ⊕ D*⁻¹ has that 1 cm (rotated), no rotation.
    estimate = np.zeros_like(reference)
    for i, step in enumerate(steps):
        estimate[i + 1] = compose(estimate[i], compose(step, np.array([0.0, 0.01, 0.0])))
    error = relative_pose_error(reference, estimate)
    assert error.trans_error_m_mean == pytest.approx(0.01, rel=1e-6)
    assert error.trans_error_m_std == pytest.approx(0.0, abs=1e-9)
    assert error.trans_error_m2_mean == pytest.approx(1e-4, rel=1e-6)
    assert error.rot_error_deg_mean == pytest.approx(0.0, abs=1e-9)
    # Every step turns 0.5 deg too far: the rotational error is that; the translational one is what the
    # extra turn does to the step, |t* - R(0.5 deg) t*| (the metric's known asymmetry).
    turned = np.zeros_like(reference)
    for i, step in enumerate(steps):
        turned[i + 1] = compose(turned[i], compose(step, np.array([0.0, 0.0, math.radians(0.5)])))
    error = relative_pose_error(reference, turned)
    assert error.rot_error_deg_mean == pytest.approx(0.5, rel=1e-6)
    lever = np.hypot(steps[:, 0], steps[:, 1]) * 2.0 * math.sin(math.radians(0.25))
    assert error.trans_error_m_mean == pytest.approx(float(np.mean(lever)), rel=1e-6)
    pairs = np.array([[0, 10], [5, 50]])
    assert relative_pose_error(reference, estimate, pairs).n == 2
    with pytest.raises(ValueError):
        relative_pose_error(reference, estimate[:-1])


def test_absolute_trajectory_error() -> None:
    truth = np.zeros((4, 3))
    estimate = np.array([[0.0, 0.1, 0.0], [0.0, -0.1, 0.0], [0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]])
    assert absolute_trajectory_error(truth, estimate) == pytest.approx(0.1)


def test_aligned_error_takes_out_a_rigid_motion_and_nothing_else() -> None:
    rng = np.random.default_rng(5)
    truth = np.column_stack([rng.uniform(-5, 5, 200), rng.uniform(-3, 3, 200), rng.uniform(-3, 3, 200)])
    # The same path in a frame turned by 2 degrees and moved by (0.3, -0.1) m.
    moved = compose(np.array([0.3, -0.1, math.radians(2.0)]), truth)
    assert absolute_trajectory_error(truth, moved) > 0.1
    assert aligned_trajectory_error(truth, moved) < 1e-9
    tx, ty, angle = rigid_alignment(moved, truth)  # the motion that lays truth onto moved
    assert (tx, ty, math.degrees(angle)) == pytest.approx((0.3, -0.1, 2.0))
    # Noise on top stays: 1 cm per axis gives ~1.4 cm RMS whatever the frame.
    noisy = moved.copy()
    noisy[:, :2] += rng.normal(0.0, 0.01, (200, 2))
    assert 0.012 < aligned_trajectory_error(truth, noisy) < 0.016
    assert math.isnan(aligned_trajectory_error(truth[:0], noisy[:0]))


def test_wall_thickness_tells_thin_from_thick_and_doubled() -> None:
    thin = np.zeros((60, 60), dtype=bool)
    thin[30, 5:55] = True  # one horizontal wall
    thin[5:55, 10] = True  # one vertical wall
    idx = np.arange(10, 50)
    thin[idx, idx] = True  # a diagonal one
    assert wall_thickness(thin).thin_fraction > 0.9
    thick = np.zeros((60, 60), dtype=bool)
    thick[28:32, 5:55] = True  # four cells thick
    assert wall_thickness(thick).thin_fraction < 0.1
    doubled = np.zeros((60, 60), dtype=bool)
    doubled[30, 5:55] = True
    doubled[32, 5:55] = True
    assert wall_thickness(doubled).thin_fraction < 0.1  # a ghost copy 10 cm beside the wall
    two = np.zeros((60, 60), dtype=bool)
    two[30:32, 5:55] = True  # a wall that fell on a cell boundary: two cells thick, still one line
    assert wall_thickness(two).thin_fraction > 0.9
    assert math.isnan(wall_thickness(np.zeros((5, 5), dtype=bool)).thin_fraction)


def test_a_save_tidies_what_a_killed_save_left(tmp_path: Path) -> None:
    first, second = two_versions()
    yaml_file = tmp_path / "map.yaml"
    save_killed_before_rename(yaml_file, first, 1)  # the image renamed, no YAML yet
    assert [p.suffix for p in tmp_path.iterdir()] in ([".tmp", ".pgm"], [".pgm", ".tmp"])
    files = save_map(second, yaml_file)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([files.image.name, "map.yaml"])
