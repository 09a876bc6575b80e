"""The map saved as the robot goes (``agent.runtime.map_saver``): written off the caller's thread, the
latest one wins, on request and every interval, a failing disk counted and survived."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from agent.runtime.map_saver import MapSaver, content_stamp_ns
from agent.slam.mapio import load_map
from agent.slam.render import OccupancyImage, occupancy_image


def image(value: float, cells: int = 40) -> OccupancyImage:
    log_odds = np.full((cells, cells), value, dtype=np.float32)
    return occupancy_image(log_odds, (-1.0, -1.0), 0.05)


class Clock:
    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


def test_due_every_interval_and_on_request(tmp_path: Path) -> None:
    clock = Clock()
    saver = MapSaver(tmp_path, 30.0, clock_s=clock)
    try:
        assert not saver.due()
        clock.now_s += 29.9
        assert not saver.due()
        clock.now_s += 0.2
        assert saver.due()
        saver.skip()  # no map yet: the interval counts from now
        assert not saver.due()
        saver.request()  # what SIGUSR1 does
        assert saver.due()
        saver.submit(image(-3.0))
        assert not saver.due() and not saver.requested
        assert saver.flush()
    finally:
        saver.close()
    assert saver.saves == 1
    assert load_map(tmp_path / "map.yaml").pixels.shape == (40, 40)


def test_interval_zero_saves_only_on_request(tmp_path: Path) -> None:
    clock = Clock()
    saver = MapSaver(tmp_path, 0.0, clock_s=clock)
    clock.now_s += 1e6
    assert not saver.due()
    saver.request()
    assert saver.due()
    saver.close()


def test_submit_returns_at_once_and_the_pair_and_previous_are_written(tmp_path: Path) -> None:
    saver = MapSaver(tmp_path, 1.0)
    try:
        t0 = time.perf_counter()
        saver.submit(image(-3.0))  # free
        handover_s = time.perf_counter() - t0
        assert saver.flush()
        saver.submit(image(3.0))  # occupied
        assert saver.flush()
    finally:
        saver.close()
    # The caller only queued it: the write (with its fsyncs) ran on the saver's thread.
    assert handover_s < 0.01
    assert saver.saves == 2 and saver.failures == 0
    assert np.all(load_map(tmp_path / "map.yaml").pixels == 0)
    assert np.all(load_map(tmp_path / "map.prev.yaml").pixels == 254)
    assert saver.counters()["map_save_max_us"] > 0


def test_a_newer_map_replaces_one_not_written_yet(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from agent.slam import mapio

    release = threading.Event()
    writing = threading.Event()
    real_save = mapio.save_map

    def slow_save(*args: object, **kwargs: object) -> object:
        writing.set()
        release.wait(5.0)
        return real_save(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(mapio, "save_map", slow_save)
    saver = MapSaver(tmp_path, 1.0)
    try:
        saver.submit(image(-3.0))
        assert writing.wait(5.0)
        saver.submit(image(0.0))  # waits: the first is being written
        saver.submit(image(3.0))  # replaces the waiting one
        release.set()
        assert saver.flush()
    finally:
        release.set()
        saver.close()
    assert saver.saves == 2 and saver.dropped == 1
    assert np.all(load_map(tmp_path / "map.yaml").pixels == 0)


def test_close_writes_what_is_waiting(tmp_path: Path) -> None:
    saver = MapSaver(tmp_path, 1.0)
    saver.submit(image(3.0))
    saver.close()
    saver.close()  # twice is fine
    assert saver.saves == 1
    assert (tmp_path / "map.yaml").is_file()
    saver.submit(image(-3.0))  # after close: ignored, no thread to write it
    assert saver.saves == 1


def test_a_failing_disk_is_counted_and_the_saver_goes_on(tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("x")
    saver = MapSaver(blocker / "maps", 1.0)
    try:
        saver.submit(image(3.0))
        assert saver.flush()
        saver.submit(image(3.0))
        assert saver.flush()
    finally:
        saver.close()
    assert saver.failures == 2 and saver.saves == 0


def test_the_next_save_is_due_its_lead_before_the_last_content_time_plus_the_interval(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each save takes 0.2 s of the saver's clock from when it was due to its commit: the next is due 1.5
    times that before the last map's content time plus the interval, so the map on disk is never more than
    one interval behind; the content time is in the image's header."""
    from agent.slam import mapio

    clock = Clock()
    real_save = mapio.save_map

    def slow_save(*args: object, **kwargs: object) -> object:
        clock.now_s += 0.2
        return real_save(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(mapio, "save_map", slow_save)
    saver = MapSaver(tmp_path, 1.0, clock_s=clock)
    try:
        assert saver.due_at_s() == pytest.approx(100.99)  # the minimum lead before any save
        clock.now_s = 100.995
        assert saver.due() and saver.seconds_until_due() == 0.0
        saver.submit(image(-3.0), fetch_s=0.0, content_s=100.995)  # taken out 5 ms after it was due
        assert saver.flush()
        # The lag, from when it was due: the 5 ms the SLAM thread took to get to it, then 0.2 s writing.
        assert saver.counters()["map_save_lag_max_us"] == pytest.approx(205_000, abs=2)
        assert saver.lead_s == pytest.approx(1.5 * 0.205)
        assert saver.due_at_s() == pytest.approx(100.995 + 1.0 - 1.5 * 0.205)
        assert saver.late == 1  # that first one took longer than the 10 ms lead of its time
        assert saver.seconds_until_due() == pytest.approx(saver.due_at_s() - clock.now_s)
        # The image names its content time.
        pgm = next(tmp_path.glob("map.*.pgm")).read_bytes()
        assert content_stamp_ns(pgm) == round(100.995e9)
        assert saver.committed_content_s == 100.995
        # The next, due on time and as slow: committed within one interval of the last content time.
        clock.now_s = saver.due_at_s() or 0.0
        content = clock.now_s
        saver.submit(image(3.0), fetch_s=0.0, content_s=content)
        assert saver.flush()
        assert clock.now_s - 100.995 <= 1.0 and saver.late == 1
    finally:
        saver.close()


def test_a_requested_save_counts_its_lag_from_the_fetch_and_no_interval_means_no_schedule(
    tmp_path: Path,
) -> None:
    clock = Clock()
    saver = MapSaver(tmp_path, 0.0, clock_s=clock)
    try:
        assert saver.due_at_s() is None and saver.seconds_until_due() is None
        saver.request()
        assert saver.seconds_until_due() == 0.0
        saver.submit(image(3.0), fetch_s=0.0, content_s=clock.now_s)
        assert saver.flush()
        assert saver.counters()["map_saves_late"] == 0  # no interval: no bound to keep
    finally:
        saver.close()
    assert content_stamp_ns(b"P5\n# vlp-agent slam\n40 40\n255\n") is None


def test_the_topological_map_is_written_beside_each_map_and_read_back_with_its_places(tmp_path: Path) -> None:
    from agent.exploration.htm import Htm
    from agent.exploration.topology import add_named_places, from_geojson, named_places, to_geojson
    from agent.slam.mapio import load_topology, topology_path

    htm = Htm()
    htm.set_regions([(((0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)), 1.0)])
    add_named_places(htm, [("desk", 0.5, 0.5)])
    saver = MapSaver(tmp_path, 0.0)
    saver.topology = lambda: to_geojson(htm)
    try:
        saver.submit(image(-3.0))
        assert saver.flush()
    finally:
        saver.close()
    assert saver.topology_saves == 1 and saver.counters()["topology_save_failures"] == 0
    back = from_geojson(load_topology(topology_path(tmp_path / "map.yaml")))
    assert named_places(back) == {"desk": (0.5, 0.5)}
    assert back.regions()[0].name == "desk"  # the room the place lies in is named after it
