"""The SLAM filter in its own process (agent.runtime.slam_worker): the same steps, map and trajectory as the
filter in the agent's process, and the agent carrying on when the process dies."""

from __future__ import annotations

import dataclasses
import math
import os
import signal
import time

import numpy as np
import pytest

from agent.config import MountConfig, SlamConfig
from agent.runtime import slam_worker
from agent.runtime.mapper import MapperStep, RbpfMapper
from agent.runtime.slam_factory import make_mapper
from agent.runtime.slam_worker import ProcessMapper
from agent.runtime.types import AbsoluteFix
from agent.slam.simlog import simulate_log
from drivers.samples import Scan
from drivers.sim.worldfile import load_world
from tests.conftest import REPO

MIN_RANGE_MM = 20


@pytest.fixture(scope="module")
def run():  # type: ignore[no-untyped-def]
    """Twelve seconds of the office route: the laser's scans as the driver gives them, with odometry."""
    world = load_world(REPO / "examples" / "worlds" / "office.toml")
    sim = simulate_log(world, 12.0, seed=3)
    geometry = sim.log.geometry
    angles = geometry.angles_rad
    scans = []
    for k, record in enumerate(sim.log.records):
        mm = np.round(record.ranges_m * 1000.0).astype(np.int32)
        mm[record.ranges_m <= 0.0] = 0  # no return: the URG's error code
        scans.append(
            (
                Scan(
                    mm,
                    float(angles[0]),
                    float(angles[1] - angles[0]),
                    MIN_RANGE_MM,
                    int(geometry.no_return_m * 1000),
                    k,
                    int(record.t_s * 1e9),
                ),
                (float(record.odom_pose[0]), float(record.odom_pose[1]), float(record.odom_pose[2])),
            )
        )
    start = tuple(float(v) for v in sim.log.records[0].reference_pose)  # type: ignore[union-attr]
    mount = MountConfig(*geometry.mount[:2], 0.0, geometry.mount[2])
    return scans, start, mount, sim.fixes[:8]


def _feed(mapper, scans, fixes, start):  # type: ignore[no-untyped-def]
    steps: list[MapperStep] = []
    pending = list(fixes)
    for scan, odom in scans:
        while pending and pending[0].t_s * 1e9 <= scan.host_time_ns:
            f = pending.pop(0).fix
            fix = AbsoluteFix(scan.host_time_ns, f.x_m, f.y_m, f.yaw_rad, np.asarray(f.covariance))
            mapper.add_fix(fix, odom)
        steps.append(mapper.update(scan, odom))
    return steps


def test_the_filter_in_its_process_gives_what_it_gives_in_the_agents(run) -> None:  # type: ignore[no-untyped-def]
    scans, start, mount, fixes = run
    config = SlamConfig(seed=4, process=False)
    here = RbpfMapper(config, mount, lambda t_ns: start)
    there = ProcessMapper(dataclasses.replace(config, process=True), mount, lambda t_ns: start)
    try:
        ours, theirs = _feed(here, scans, fixes, start), _feed(there, scans, fixes, start)
        assert [s.kind for s in theirs] == [s.kind for s in ours]
        updated = [k for k, s in enumerate(ours) if s.fix is not None]
        assert len(updated) >= 5
        for k in updated:
            a, b = ours[k].fix, theirs[k].fix
            assert b is not None and a is not None
            assert (b.x_m, b.y_m, b.yaw_rad) == (a.x_m, a.y_m, a.yaw_rad)
            np.testing.assert_array_equal(b.covariance, a.covariance)
        assert there.pose() == here.pose()
        np.testing.assert_array_equal(there.trajectory(), here.trajectory())
        np.testing.assert_array_equal(there.map_image().pixels, here.map_image().pixels)
        counters = there.counters()
        assert counters["fixes_applied"] == here.counters()["fixes_applied"] > 0
        assert counters["worker_peak_rss_kb"] > 10_000 and counters["worker_restarts"] == 0
        # The interpreter's and libraries' pages that this process maps too: part of the child's peak.
        assert 0 < counters["worker_shared_kb"] < counters["worker_peak_rss_kb"]
    finally:
        there.close()


def test_make_mapper_puts_the_filter_in_a_process_by_default(run) -> None:  # type: ignore[no-untyped-def]
    _, start, mount, _ = run
    mapper, why = make_mapper(SlamConfig(), mount, lambda t_ns: start)
    try:
        assert isinstance(mapper, ProcessMapper), why
    finally:
        if mapper is not None:
            mapper.close()


def test_a_dead_slam_process_is_reported_and_replaced(run, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    scans, start, mount, _ = run
    monkeypatch.setattr(slam_worker, "_RESTART_AFTER_S", 0.3)
    mapper = ProcessMapper(SlamConfig(seed=4), mount, lambda t_ns: start)
    try:
        for scan, odom in scans[:20]:
            assert mapper.update(scan, odom).kind != "rejected"
        assert mapper._process is not None
        mapper._process.kill()
        mapper._process.wait(5)
        scan, odom = scans[20]
        step = mapper.update(scan, odom)
        assert step.kind == "rejected" and "SLAM process" in step.reason
        # Within the restart delay: still down, said so; no new process for every scan.
        step = mapper.update(*scans[21])
        assert step.kind == "rejected" and "down" in step.reason
        time.sleep(0.4)
        step = mapper.update(*scans[22])
        # A new process, a new map from the fused pose.
        assert step.kind == "first"
        assert mapper.counters()["worker_restarts"] == 1
        assert mapper.update(*scans[23]).kind != "rejected"
    finally:
        mapper.close()
    # Closed for good: no new process for a late call.
    assert mapper.map_image() is None and mapper._process is None


def test_the_slam_process_outlives_ctrl_c_and_systemds_stop_until_the_agent_hangs_up(run) -> None:  # type: ignore[no-untyped-def]
    scans, start, mount, _ = run
    mapper = ProcessMapper(SlamConfig(seed=4), mount, lambda t_ns: start)
    try:
        for scan, odom in scans[:5]:
            mapper.update(scan, odom)
        process = mapper._process
        assert process is not None
        for sig in (signal.SIGINT, signal.SIGTERM):
            os.kill(process.pid, sig)
        time.sleep(0.3)
        assert process.poll() is None
        assert mapper.update(*scans[5]).kind != "rejected"
        assert mapper.pose() is not None and all(math.isfinite(v) for v in mapper.pose() or ())
    finally:
        mapper.close()
    assert process.wait(5) == 0


def test_a_replaced_slam_process_continues_the_last_saved_map(run, monkeypatch, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from agent.slam.mapio import save_map

    scans, start, mount, _ = run
    monkeypatch.setattr(slam_worker, "_RESTART_AFTER_S", 0.3)
    mapper = ProcessMapper(SlamConfig(seed=4), mount, lambda t_ns: start)
    try:
        for scan, odom in scans[:100]:
            mapper.update(scan, odom)
        saved = mapper.map_image()
        assert saved is not None
        # What the map saver wrote last.
        mapper.resume_map = lambda: save_map(saved, tmp_path / "map.yaml").yaml
        assert mapper._process is not None
        mapper._process.kill()
        mapper._process.wait(5)
        assert mapper.update(*scans[100]).kind == "rejected"
        time.sleep(0.4)
        assert mapper.update(*scans[101]).kind == "first"
        assert mapper.counters()["worker_restarts"] == 1
        after = mapper.map_image()
    finally:
        mapper.close()

    def occupied(image):  # type: ignore[no-untyped-def]
        rows, cols = np.nonzero(image.pixels == 0)
        h = image.pixels.shape[0]
        return set(
            zip(
                (np.round(image.origin[0] / 0.05) + cols).astype(int).tolist(),
                (np.round(image.origin[1] / 0.05) + h - 1 - rows).astype(int).tolist(),
                strict=True,
            )
        )

    # The new process's map holds what the old one had saved, not just its first scan.
    assert len(occupied(saved)) > 100
    assert len(occupied(saved) & occupied(after)) > 0.95 * len(occupied(saved))
