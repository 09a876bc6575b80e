"""Issue 21's lifelong-mapping acceptance on a simulated drive (``benchmarks/map_continue.py``): the west
part mapped, saved to disk, loaded; a new filter seeded with it maps the east and comes back west over it:
one consistent map, ATE <= 5 cm over both runs, the first map's walls still where they were."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

from tests.integration.test_agent_accuracy import REPO

_SPEC = importlib.util.spec_from_file_location("map_continue", REPO / "benchmarks" / "map_continue.py")
assert _SPEC is not None and _SPEC.loader is not None
map_continue = importlib.util.module_from_spec(_SPEC)
sys.modules[_SPEC.name] = map_continue
_SPEC.loader.exec_module(map_continue)


@pytest.mark.slow
def test_west_then_east_from_the_saved_map_is_one_consistent_map(tmp_path: Path) -> None:
    # 150 s: the cut comes at 65 s, the east run then crosses S3 and N3 and comes back west into N2. The
    # second start pose is given 5 cm off: the saved walls put it right.
    result = map_continue.measure(150.0, vlp_fixes=False, start_error_m=0.05, seed=0, folder=tmp_path)
    assert result["west_x_max_m"] < 10.0 < result["east_x_range_m"][1]
    assert result["east_x_range_m"][0] < 10.0  # back over the west part
    assert result["ate_m"] <= 0.05
    assert result["east_ate_m"] <= 0.05
    assert result["first_map_kept"] > 0.9
    assert result["odometry_ate_m"] > 0.2  # what the filter had to correct
