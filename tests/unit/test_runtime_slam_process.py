"""The SLAM filter in its own process (agent.runtime.slam_worker): the same steps, map and trajectory as the
filter in the agent's process, and the agent carrying on when the process dies."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import signal
import threading
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


@contextlib.contextmanager
def _busy(run, monkeypatch, tmp_path, stuck: bool):  # type: ignore[no-untyped-def]
    """A SLAM process (tests/busy_slam_worker.py) past its first filter update, and a thread whose update
    it is busy in (the file it touches says it is in that update): yields the mapper, its process, the
    thread and the thread's steps; closes the mapper on the way out (the test's stop, or a failure's)."""
    scans, start, mount, _ = run
    busy = tmp_path / "busy"
    monkeypatch.setenv("VLP_TEST_SLAM_BUSY", str(busy))
    monkeypatch.setenv("VLP_TEST_SLAM_STUCK", "1" if stuck else "0")
    monkeypatch.setattr(ProcessMapper, "worker_module", "tests.busy_slam_worker")
    mapper = ProcessMapper(SlamConfig(seed=4), mount, lambda t_ns: start)
    try:
        k = 0
        while mapper.counters().get("filter_updates", 0) < 1:
            assert mapper.update(*scans[k]).kind != "rejected"
            k += 1
        steps: list[MapperStep] = []
        thread = threading.Thread(target=lambda: steps.append(mapper.update(*scans[k])), daemon=True)
        thread.start()
        deadline = time.monotonic() + 60.0  # a hang guard, not a timing: the process gets there at any load
        while not busy.exists():
            assert time.monotonic() < deadline and thread.is_alive()
            time.sleep(0.05)
        process = mapper._process
        assert process is not None
        yield mapper, process, thread, steps
    finally:
        mapper.close()


def test_a_slam_process_busy_in_a_long_update_leaves_it_at_the_stop_and_hands_over_its_map(
    run, monkeypatch, tmp_path, caplog
) -> None:  # type: ignore[no-untyped-def]
    """The stop reaches the process inside the update: it leaves it at its next give_way, the SLAM thread's
    wait ends at once (its scan rejected, not an error), the final map and trajectory are answered, and
    the process exits by itself when the agent hangs up. (The bounds are hang guards, not timings.) The
    thread's step says either that the agent is stopping (the stop woke the wait first) or that the
    process left its update for the stop (its answer was already there when the wait woke: seen beside a
    CPU hog); both are the stop's."""
    caplog.set_level(logging.INFO, logger="agent.runtime.slam_worker")
    with _busy(run, monkeypatch, tmp_path, stuck=False) as (mapper, process, thread, steps):
        mapper.begin_stop(grace_s=60.0)
        thread.join(60.0)
        assert not thread.is_alive()
        assert steps[0].kind == "rejected", steps[0]
        assert steps[0].reason.startswith("the agent is stopping") or steps[0].reason.endswith(
            "left its filter update unfinished for the stop"
        ), steps[0].reason
        image = mapper.map_image()
        assert image is not None and image.pixels.size > 0
        assert mapper.trajectory().shape[0] >= 1
        # No scan reaches the filter any more, and no new process is started for one.
        assert mapper.update(*run[0][-1]).kind == "rejected"
    assert process.returncode == 0  # it exited at the hang-up: not killed
    messages = [r.getMessage() for r in caplog.records]
    assert any("left its filter update unfinished" in m for m in messages), messages
    assert any("SLAM process stopped (exit status 0)" in m for m in messages), messages
    assert not any(r.levelno >= logging.WARNING for r in caplog.records), messages
    assert mapper.counters()["worker_interrupted"] == 1


def test_a_slam_process_that_does_not_answer_the_stop_is_killed_at_the_deadline_and_the_log_says_so(
    run, monkeypatch, tmp_path, caplog
) -> None:  # type: ignore[no-untyped-def]
    """A filter stuck in one long computation (no give_way) cannot leave it: the SLAM thread's wait still
    ends at once; the final map is waited for until the stop's deadline, then the process is killed, and
    the log says the final map was not taken out."""
    with _busy(run, monkeypatch, tmp_path, stuck=True) as (mapper, process, thread, steps):
        mapper.begin_stop(grace_s=1.0)
        thread.join(60.0)
        assert not thread.is_alive() and steps[0].kind == "rejected"
        assert mapper.map_image() is None
    assert process.returncode == -signal.SIGKILL
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert any("within 1 s of the stop" in m and "final map was not taken out" in m for m in errors), errors


def test_a_slam_process_that_does_not_exit_after_the_hang_up_is_killed_and_the_log_says_nothing_was_lost(
    run, monkeypatch, tmp_path, caplog
) -> None:  # type: ignore[no-untyped-def]
    """No final map asked for (no map folder, localization): at the hang-up a process stuck in an update
    has until the stop's deadline (at least 2 s) to exit; then it is killed, with a warning that no final
    map was asked of it (nothing lost), not an error."""
    with _busy(run, monkeypatch, tmp_path, stuck=True) as (mapper, process, thread, _):
        mapper.begin_stop(grace_s=0.5)
        thread.join(60.0)
    assert process.returncode == -signal.SIGKILL
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("had not exited" in m and "no final map was asked of it" in m for m in warnings), warnings
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
