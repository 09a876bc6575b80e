"""The map saved at a stop (agent.runtime.mapper.save_final_map): the filter's map first, then the final
optimisation and the optimised map over it, the first kept as map.prev.yaml; nothing lost where the
optimisation gives no map back."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agent.config import MountConfig, SlamConfig
from agent.runtime.mapper import RbpfMapper, save_final_map
from agent.slam import mapio
from agent.slam.render import MapPath, occupancy_image


class FinishingMapper:
    """A mapper whose map and trajectory change when it is finished (``finishes``: whether it runs)."""

    name = "fake"

    def __init__(self, finishes: bool, map_after: bool = True, updates: int = 3) -> None:
        self.finishes = finishes
        self.map_after = map_after
        self.updates = updates
        self.finished = False
        self.finish_calls = 0

    def counters(self) -> dict[str, int]:
        return {"filter_updates": self.updates}

    def map_image(self) -> Any:
        if self.finished and not self.map_after:
            return None  # (a SLAM process killed in its optimisation: nothing more comes out)
        log_odds = np.full((40, 60), -2.0, dtype=np.float32)
        log_odds[5 if self.finished else 30, :] = 3.0  # the wall moves with the optimisation
        return occupancy_image(log_odds, (0.0, 0.0), 0.05)

    def trajectory(self) -> np.ndarray:
        shift = 0.5 if self.finished else 0.0
        return np.array([[0.1, 0.1 + shift, 0.0], [2.0, 0.5 + shift, 0.0]])

    def finish(self) -> bool:
        self.finish_calls += 1
        self.finished = self.finishes
        return self.finishes


def _pixels(yaml_path: Path) -> np.ndarray:
    return mapio.load_map(yaml_path).pixels


def test_an_optimised_map_is_saved_over_the_filters_which_is_kept_beside_it(tmp_path: Path) -> None:
    mapper = FinishingMapper(finishes=True)
    drawn: list[np.ndarray] = []

    def paths(slam: np.ndarray) -> list[MapPath]:
        drawn.append(slam)
        return [MapPath("SLAM estimate", slam[:, :2], (0, 0, 255))]

    files, optimised = save_final_map(mapper, tmp_path, paths_for=paths)
    assert optimised and mapper.finish_calls == 1
    assert [p.name for p in files[:1]] == ["map.yaml"] and all(p.exists() for p in files)
    final, first = _pixels(tmp_path / "map.yaml"), _pixels(tmp_path / "map.prev.yaml")
    assert not np.array_equal(final, first)  # the optimised map, and the filter's beside it
    # Each picture drew the trajectory of the map it shows.
    assert [float(p[0, 1]) for p in drawn] == [0.1, 0.6]


def test_without_the_optimisation_the_map_is_saved_once(tmp_path: Path) -> None:
    mapper = FinishingMapper(finishes=False)
    files, optimised = save_final_map(mapper, tmp_path)
    assert not optimised and mapper.finish_calls == 1
    assert (tmp_path / "map.yaml").exists() and not (tmp_path / "map.prev.yaml").exists()
    assert all(p.exists() for p in files)


def test_a_map_lost_in_the_optimisation_leaves_the_one_saved_first(tmp_path: Path) -> None:
    mapper = FinishingMapper(finishes=True, map_after=False)
    files, optimised = save_final_map(mapper, tmp_path)
    assert optimised  # it ran; its map could not be taken out after it
    assert all(p.exists() for p in files) and not (tmp_path / "map.prev.yaml").exists()
    assert _pixels(tmp_path / "map.yaml")[40 - 1 - 30, 0] == 0  # the filter's wall, as saved first


def test_no_map_no_optimisation(tmp_path: Path) -> None:
    mapper = FinishingMapper(finishes=True, updates=0)
    assert save_final_map(mapper, tmp_path) == ([], False)
    assert mapper.finish_calls == 0 and not any(tmp_path.iterdir())


def test_a_filter_not_started_has_nothing_to_finish() -> None:
    mapper = RbpfMapper(SlamConfig(process=False), MountConfig(), lambda t_ns: None)
    assert mapper.finish() is False


@pytest.mark.parametrize("key", [True, False])
def test_the_config_key_reaches_the_filter(key: bool) -> None:
    from agent.runtime.mapper import front_end_filter
    from agent.slam.rbpf import RbpfConfig

    loop = front_end_filter(SlamConfig(loop_final_scan_chain=key), RbpfConfig().proposal)["loop_closure"]
    assert (loop.final_scan_chain is not None) is key
