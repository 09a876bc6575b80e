"""The SLAM loop takes the map out of the mapper once for everyone due at that scan (the navigation, the
flight recorder's ``/map``, the saver), and not at all when nobody is."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from agent.config import parse_config
from agent.fusion import PoseFilter
from agent.runtime.devices import Devices
from agent.runtime.hotpath import HotPath
from agent.runtime.loop_state import LoopState
from agent.runtime.mailbox import BoundedQueue
from agent.runtime.map_saver import MapSaver
from agent.runtime.slam_loop import SlamLoop
from agent.slam.render import occupancy_image
from tests.unit.test_recording import OFFICE


class Mapper:
    name = "fake"

    def __init__(self) -> None:
        self.fetches = 0
        self.image = occupancy_image(np.zeros((20, 20), dtype=np.float32), (0.0, 0.0), 0.05)

    def map_image(self) -> Any:
        self.fetches += 1
        return self.image

    def counters(self) -> dict[str, int]:
        return {"filter_updates": 1}


def test_one_fetch_serves_every_one_due_and_none_is_made_for_nobody(tmp_path: Path) -> None:
    config = parse_config(f'[sim]\nworld = "{OFFICE}"\n[recorder]\nmap_period_s = 5\n')
    now = {"ns": 100 * 10**9}
    state = LoopState(config, Devices(), lambda: now["ns"])
    recorded: list[tuple[str, Any]] = []
    state.set_recorder(lambda kind, t_ns, sample: recorded.append((kind, sample)))
    clock = {"s": 100.0}
    saver = MapSaver(tmp_path, 1.0, clock_s=lambda: clock["s"])
    navigation: list[Any] = []
    mapper = Mapper()
    loop = SlamLoop(
        state,
        mapper=mapper,
        fusion=PoseFilter(np.zeros(3), np.eye(3) * 1e-4, 0),
        scans=BoundedQueue(4),
        slam_fixes=BoundedQueue(4),
        hot_path=HotPath(lambda: False),
        odometry_track=None,
        on_map=navigation.append,
        map_period_s=2.0,
        saver=saver,
    )
    try:
        clock["s"] += 1.0  # the saver is due too
        loop._share_map(mapper, mapped=True)
        assert mapper.fetches == 1
        assert navigation == [mapper.image]
        assert [kind for kind, _ in recorded] == ["map"] and recorded[0][1][1] is mapper.image
        assert saver.flush() and saver.saves == 1
        # Nobody due (no new scan for the navigation and the recorder, the saver just served): no fetch.
        loop._share_map(mapper, mapped=False)
        loop._share_map(mapper, mapped=True)
        assert mapper.fetches == 1
        # Only the saver due, no scan since: one fetch, for it alone.
        clock["s"] += 1.0
        loop._share_map(mapper, mapped=False)
        assert mapper.fetches == 2 and len(navigation) == 1 and len(recorded) == 1
        assert saver.flush() and saver.saves == 2
        # The navigation's period up after a scan: one fetch, the recorder's 5 s not yet.
        now["ns"] += 2 * 10**9
        loop._share_map(mapper, mapped=True)
        assert mapper.fetches == 3 and len(navigation) == 2 and len(recorded) == 1
        assert state.counts["map_fetches"] == 3
    finally:
        saver.close()
