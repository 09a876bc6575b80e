"""The agent's SLAM map at a stop, on a real log (exp1, the robot's own URG laser): the filter's map saved,
then the final optimisation run (in the agent's process and in the SLAM process after its stop) and the
optimised map saved over it, the filter's kept beside it as map.prev.yaml."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agent.config import MountConfig, SlamConfig
from agent.runtime.mapper import RbpfMapper, ScanMapper, save_final_map
from agent.runtime.slam_worker import ProcessMapper
from agent.slam import mapio
from agent.slam.logs import read_log
from drivers.samples import Scan
from tests.conftest import DATA


@pytest.fixture(scope="module")
def exp1() -> tuple[list[tuple[Scan, tuple[float, float, float]]], MountConfig]:
    """exp1's scans as the URG driver gives them (mm, 0 = no return), with their odometry."""
    path = DATA / "slam" / "breezyslam" / "exp1.dat"
    if not path.exists():
        pytest.skip(f"reference data not found at {DATA} (set VLP_SHARED to the shared folder)")
    log = read_log(path, "breezyslam")
    g = log.geometry
    angles = g.angles_rad
    scans = []
    for k, record in enumerate(log.records):
        mm = np.round(record.ranges_m * 1000.0).astype(np.int32)
        mm[record.ranges_m <= 0.0] = 0
        step = float(angles[1] - angles[0])
        scan = Scan(mm, float(angles[0]), step, 20, int(g.no_return_m * 1000), k, int(record.t_s * 1e9))
        odom = record.odom_pose
        scans.append((scan, (float(odom[0]), float(odom[1]), float(odom[2]))))
    return scans, MountConfig(*g.mount[:2], 0.0, g.mount[2])


def _map_the_log(mapper: ScanMapper, scans: list[Any]) -> None:
    for scan, odom in scans:
        assert mapper.update(scan, odom).kind != "rejected"


def _check_saved(
    tmp_path: Path, files: list[Path], optimised: bool, before: np.ndarray, after: np.ndarray
) -> None:
    assert optimised
    assert all(p.exists() for p in files) and (tmp_path / "map.prev.yaml").exists()
    final = mapio.load_map(tmp_path / "map.yaml").pixels
    first = mapio.load_map(tmp_path / "map.prev.yaml").pixels
    assert final.shape != first.shape or not np.array_equal(final, first)
    # The loop's correction spread along the path: the trajectory moved, by more than centimetres somewhere.
    assert before.shape == after.shape and float(np.max(np.hypot(*(after - before)[:, :2].T))) > 0.05


def test_the_agents_filter_is_finished_and_its_map_saved_twice(exp1, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    scans, mount = exp1
    mapper = RbpfMapper(SlamConfig(seed=0, process=False), mount, lambda t_ns: (0.0, 0.0, 0.0))
    _map_the_log(mapper, scans)
    assert mapper.counters()["final_scan_edges"] == -1
    before = mapper.trajectory().copy()
    files, optimised = save_final_map(mapper, tmp_path)
    _check_saved(tmp_path, files, optimised, before, mapper.trajectory())
    edges = mapper.counters()["final_scan_edges"]
    assert edges > 0.9 * (mapper.counters()["filter_updates"] - 1)  # nearly every step registered


def test_with_the_key_off_the_map_is_the_filters_own(exp1, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    scans, mount = exp1
    config = SlamConfig(seed=0, process=False, loop_final_scan_chain=False)
    mapper = RbpfMapper(config, mount, lambda t_ns: (0.0, 0.0, 0.0))
    _map_the_log(mapper, scans[:300])
    files, optimised = save_final_map(mapper, tmp_path)
    assert not optimised and files and not (tmp_path / "map.prev.yaml").exists()
    assert mapper.counters()["final_scan_edges"] == -1


def test_the_slam_process_finishes_its_filter_after_the_stop(exp1, tmp_path: Path, caplog) -> None:  # type: ignore[no-untyped-def]
    """As `vlp-agent run` stops with the filter in its own process: the stop first, then the map, the
    optimisation and the map again, all answered within the stop's grace (a hang guard here, not a
    timing), and the process exits by itself at the hang-up."""
    caplog.set_level(logging.INFO, logger="agent.runtime.slam_worker")
    scans, mount = exp1
    mapper = ProcessMapper(SlamConfig(seed=0, process=True), mount, lambda t_ns: (0.0, 0.0, 0.0))
    try:
        _map_the_log(mapper, scans)
        before = mapper.trajectory().copy()
        mapper.begin_stop(grace_s=120.0)
        files, optimised = save_final_map(mapper, tmp_path)
        _check_saved(tmp_path, files, optimised, before, mapper.trajectory())
        assert mapper.counters()["final_scan_edges"] > 0
        process = mapper._process
        assert process is not None
    finally:
        mapper.close()
    assert process.returncode == 0  # it exited at the hang-up: not killed
    assert not any(r.levelno >= logging.WARNING for r in caplog.records), [
        r.getMessage() for r in caplog.records
    ]
