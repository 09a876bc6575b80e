"""Continuing a saved map (``[slam] mode = "continue"``): the saved grid seeds the filter, survives a loop
closure's rebuild, the robot maps on from it; and the config's checks on the map it names."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from agent.config import SlamMode, parse_config
from agent.runtime.mapper import prior_log_odds
from agent.slam.grid import LogOddsModel
from agent.slam.mapio import load_map, save_map
from agent.slam.metrics import absolute_trajectory_error
from agent.slam.rbpf import MapMode, RbpfConfig, RbpfSlam
from agent.slam.render import OccupancyImage, occupancy_image
from drivers.errors import ConfigError
from tests.unit.test_config import sim_config
from tests.unit.test_slam_filter import LASER, drive, true_map


@pytest.fixture(scope="module")
def loop() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return drive()


def cells(image: OccupancyImage, value: int) -> set[tuple[int, int]]:
    """World cells (integer multiples of the cell size, lower-left corners) holding ``value``."""
    rows, cols = np.nonzero(image.pixels == value)
    h = image.pixels.shape[0]
    x = image.origin[0] + cols * image.resolution_m
    y = image.origin[1] + (h - 1 - rows) * image.resolution_m
    return set(
        zip(
            np.round(x / image.resolution_m).astype(int),
            np.round(y / image.resolution_m).astype(int),
            strict=True,
        )
    )


def seeded_map(slam: RbpfSlam) -> OccupancyImage:
    window = slam.map_window()
    assert window is not None
    return occupancy_image(window[0], window[1], 0.05)


@pytest.mark.parametrize("mode", [MapMode.PER_PARTICLE, MapMode.SHARED])
def test_a_saved_map_seeds_every_particle_cell_for_cell(
    loop: tuple[np.ndarray, ...], tmp_path: Path, mode: MapMode
) -> None:
    saved = load_map(true_map(loop, tmp_path))
    slam = RbpfSlam(LASER, RbpfConfig(particles=4, map_mode=mode))
    log_odds, origin = prior_log_odds(saved, LogOddsModel())
    slam.seed_map(log_odds.astype(np.float32), origin)
    for particle in range(4):
        window = slam.map_window(particle)
        assert window is not None
        again = occupancy_image(window[0], window[1], 0.05)
        for value in (0, 254):
            assert cells(again, value) == cells(saved, value), (particle, value)
    assert len(cells(saved, 0)) > 500 and len(cells(saved, 254)) > 5000


def test_the_seed_survives_a_rebuild_of_the_map(loop: tuple[np.ndarray, ...], tmp_path: Path) -> None:
    saved = load_map(true_map(loop, tmp_path))
    slam = RbpfSlam(LASER, RbpfConfig(particles=4))
    slam.seed_map(*_prior(saved))
    # What a loop closure does once it has optimised the graph: the map again from the nodes' scans, which
    # hold only this run's scans; the saved part must come back under them.
    slam._rebuild_maps(np.zeros((0, 3)))
    again = seeded_map(slam)
    assert cells(again, 0) == cells(saved, 0)


def _prior(saved: OccupancyImage) -> tuple[np.ndarray, tuple[float, float]]:
    log_odds, origin = prior_log_odds(saved, LogOddsModel())
    return log_odds.astype(np.float32), origin


def test_continuing_from_the_saved_map_corrects_a_start_pose_a_new_map_keeps(
    loop: tuple[np.ndarray, ...], tmp_path: Path
) -> None:
    """The robot restarts half way round the loop with its start pose given 10 cm off: seeded with the
    room's saved map, the first update's search matches the known walls and the filter lands in the saved
    map's frame (within 4 cm over the rest of the loop); a new map keeps the 10 cm error as its frame. The
    old part of the map is still there at the end."""
    times, truth, odometry, ranges = loop
    saved = load_map(true_map(loop, tmp_path))
    half = len(times) // 2
    start = (float(truth[half, 0]) + 0.1, float(truth[half, 1]), float(truth[half, 2]))

    def run(seeded: bool) -> tuple[RbpfSlam, float]:
        slam = RbpfSlam(LASER, RbpfConfig(particles=8, initial_pose=start))
        if seeded:
            slam.seed_map(*_prior(saved))
        estimate = []
        for i in range(half, len(times)):
            slam.process(float(times[i]), ranges[i], odometry[i])
            estimate.append(slam.pose(odometry[i]))
        return slam, absolute_trajectory_error(truth[half:], np.array(estimate))

    slam, ate = run(seeded=True)
    _, ate_new_map = run(seeded=False)
    assert ate < 0.04
    assert ate_new_map > 0.07
    after = seeded_map(slam)
    kept = cells(saved, 0) & cells(after, 0)
    assert len(kept) > 0.9 * len(cells(saved, 0))


def test_seeding_after_the_first_scan_is_refused(loop: tuple[np.ndarray, ...], tmp_path: Path) -> None:
    times, _truth, odometry, ranges = loop
    saved = load_map(true_map(loop, tmp_path))
    slam = RbpfSlam(LASER, RbpfConfig(particles=2))
    slam.process(float(times[0]), ranges[0], odometry[0])
    with pytest.raises(ValueError, match="before the first scan"):
        slam.seed_map(*_prior(saved))


def test_a_rotated_map_cannot_be_continued() -> None:
    image = OccupancyImage(np.full((4, 4), 254, dtype=np.uint8), 0.05, (0.0, 0.0, 0.3))
    with pytest.raises(ValueError, match="rotated"):
        prior_log_odds(image, LogOddsModel())


# -- the config -------------------------------------------------------------------------------------------
def saved_map(tmp_path: Path, resolution_m: float = 0.05) -> Path:
    log_odds = np.full((40, 40), -3.0, dtype=np.float32)
    log_odds[0, :] = 3.0
    return save_map(
        occupancy_image(log_odds, (-1.0, -1.0), resolution_m), tmp_path / "maps" / "map.yaml"
    ).yaml


def test_continue_and_the_save_interval_are_read(tmp_path: Path) -> None:
    yaml = saved_map(tmp_path)
    config = parse_config(sim_config(f'[slam]\nmode = "continue"\nmap = "{yaml}"\nsave_interval_s = 5.0\n'))
    assert config.slam.mode is SlamMode.CONTINUE and config.slam.map == yaml
    assert config.slam.save_interval_s == 5.0
    assert parse_config(sim_config()).slam.save_interval_s == 30.0


def truncate_image(yaml: Path) -> None:
    image = yaml.parent / next(
        line.split(":", 1)[1].strip() for line in yaml.read_text().splitlines() if line.startswith("image:")
    )
    image.write_bytes(image.read_bytes()[:-100])


@pytest.mark.parametrize(
    ("slam", "spoil", "words"),
    [
        ('mode = "continue"\n', None, "missing"),
        ('mode = "localization"\n', None, "missing"),
        ('mode = "continue"\nmap = "{missing}"\n', None, "no such map file"),
        ('mode = "continue"\nmap = "{yaml}"\n', truncate_image, "PGM data truncated"),
        ('mode = "localization"\nmap = "{yaml}"\n', truncate_image, "PGM data truncated"),
        ('mode = "continue"\nmap = "{yaml}"\n', lambda y: y.write_text("image: x.pgm\n"), "resolution"),
        ('mode = "continue"\nmap = "{yaml}"\nresolution_m = 0.1\n', None, "0.05 m cells"),
        ('map = "{yaml}"\n', None, 'only used with mode = "localization" or "continue"'),
    ],
)
def test_a_missing_truncated_or_mismatched_map_is_a_clear_error(
    tmp_path: Path, slam: str, spoil: object, words: str
) -> None:
    yaml = saved_map(tmp_path)
    if callable(spoil):
        spoil(yaml)
    text = slam.format(yaml=yaml, missing=tmp_path / "nothing.yaml")
    with pytest.raises(ConfigError) as caught:
        parse_config(sim_config("[slam]\n" + text))
    assert caught.value.key == "slam.map"
    assert words in str(caught.value)


def test_a_negative_save_interval_is_refused() -> None:
    with pytest.raises(ConfigError, match="save_interval_s"):
        parse_config(sim_config("[slam]\nsave_interval_s = -1.0\n"))


def test_the_localization_map_may_have_another_resolution(tmp_path: Path) -> None:
    yaml = saved_map(tmp_path, 0.1)
    config = parse_config(sim_config(f'[slam]\nmode = "localization"\nmap = "{yaml}"\n'))
    assert config.slam.mode is SlamMode.LOCALIZATION
    assert math.isclose(load_map(yaml).resolution_m, 0.1)


def _seeded_with_nodes(loop: tuple[np.ndarray, ...], tmp_path: Path) -> tuple[RbpfSlam, np.ndarray]:
    """A filter seeded with the saved map, its first scan taken, and 70 graph nodes of that scan along a
    short line (what a rebuild integrates), with their poses."""
    times, truth, odometry, ranges = loop
    slam = RbpfSlam(LASER, RbpfConfig(particles=4, initial_pose=tuple(truth[0])))
    slam.seed_map(*_prior(load_map(true_map(loop, tmp_path))))
    slam.process(float(times[0]), ranges[0], odometry[0])
    slam._node_scans = slam._node_scans[:1] * 70
    poses = np.tile(truth[0], (70, 1))
    poses[:, 0] += np.linspace(0.0, 0.3, 70)
    return slam, poses


def test_a_rebuild_starts_from_the_seed_without_clearing_the_maps_first(
    loop: tuple[np.ndarray, ...], tmp_path: Path
) -> None:
    """The rebuild builds its window aside from the saved map's cells (``_prior_window``): the same window
    that clearing the maps and putting the seed back gave, so the rebuilt map is unchanged by building it
    aside."""
    import copy

    slam, _ = _seeded_with_nodes(loop, tmp_path)
    extent = slam.maps.extent(0)
    assert extent is not None
    # A window larger than the seed's on every side, and one inside it.
    for whole in (
        type(extent)(extent.ty0 - 2, extent.tx0 - 1, extent.ty1 + 3, extent.tx1 + 2),
        type(extent)(extent.ty0 + 1, extent.tx0 + 1, extent.ty1 - 1, extent.tx1 - 2),
    ):
        cleared = copy.deepcopy(slam)
        cleared.maps.clear()
        cleared._put_prior()
        window = slam._prior_window(whole)
        assert np.count_nonzero(window) > 1000
        np.testing.assert_array_equal(window, cleared.maps.gather([0], whole))


def test_a_rebuild_left_half_way_leaves_the_maps_as_they_were(
    loop: tuple[np.ndarray, ...], tmp_path: Path
) -> None:
    """A ``give_way`` that raises inside the rebuild (the agent's SLAM process stopping) leaves every
    particle's map as it was before the loop closure, not cleared or half rebuilt."""

    class Stop(Exception):
        pass

    slam, poses = _seeded_with_nodes(loop, tmp_path)
    before = [slam.map_window(p) for p in range(4)]

    def give_way() -> None:
        raise Stop

    slam.give_way = give_way
    with pytest.raises(Stop):
        slam._rebuild_maps(poses + np.array([0.5, 0.0, 0.0]))
    for p, old in enumerate(before):
        now = slam.map_window(p)
        assert now is not None and old is not None
        np.testing.assert_array_equal(now[0], old[0])
        assert now[1] == old[1]
