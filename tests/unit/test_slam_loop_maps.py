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
from agent.runtime.mapper import MapperStep
from agent.runtime.slam_loop import SlamLoop
from agent.runtime.types import AbsoluteFix
from agent.slam.render import occupancy_image
from drivers.samples import Scan
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


def _loop(state: LoopState, mapper: Any, on_map: Any, saver: MapSaver | None) -> SlamLoop:
    """A SLAM loop over ``mapper``, no wheels (the fused pose is its odometry), the map every 2 s."""
    return SlamLoop(
        state,
        mapper=mapper,
        fusion=PoseFilter(np.zeros(3), np.eye(3) * 1e-4, 0),
        scans=BoundedQueue(4),
        slam_fixes=BoundedQueue(4),
        hot_path=HotPath(lambda: False),
        odometry_track=None,
        on_map=on_map,
        map_period_s=2.0,
        saver=saver,
    )


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
    loop = _loop(state, mapper, on_map=navigation.append, saver=saver)
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


class StepMapper(Mapper):
    """Answers each scan with the next of ``steps``."""

    def __init__(self, steps: list[MapperStep]) -> None:
        super().__init__()
        self.steps = steps

    def add_fix(self, fix: AbsoluteFix, odom_pose: Any) -> None:
        pass

    def update(self, scan: Scan, odom_pose: Any) -> MapperStep:
        return self.steps.pop(0)


def test_scans_the_mapper_turned_away_are_not_counted_as_poses_the_fusion_rejected() -> None:
    """``slam_fused + slam_rejected`` is the count of SLAM poses handed to the fusion, each recorded on
    ``/slam/pose`` (the flight recorder's check holds the recording to it); what the mapper did with each scan
    is counted apart (``slam_scans_<kind>``): a scan it rejected, or the one in flight when the agent stopped
    (a SLAM process answers it ``rejected``), gave no pose."""
    config = parse_config(f'[sim]\nworld = "{OFFICE}"\n')
    state = LoopState(config, Devices(), lambda: 10**9)
    recorded: list[str] = []
    state.set_recorder(lambda kind, t_ns, sample: recorded.append(kind))
    pose = AbsoluteFix(10**9, 0.0, 0.0, 0.0, np.eye(3) * 1e-4)
    mapper = StepMapper(
        [
            MapperStep("updated", fix=pose),
            MapperStep("gated"),
            MapperStep(
                "rejected",
                reason="the SLAM process left its filter update unfinished for the stop",
                stopped=True,
            ),
        ]
    )
    loop = _loop(state, mapper, on_map=None, saver=None)
    scan = Scan(np.full(10, 1000, dtype=np.int32), -0.5, 0.1, 20, 5600, 0, 10**9)
    for _ in range(3):
        assert loop._map_scan(mapper, scan)
    counts = state.counts
    assert recorded.count("slam_pose") == 1 == counts.get("slam_fused", 0) + counts.get("slam_rejected", 0)
    assert counts["slam_scans_updated"] == counts["slam_scans_gated"] == counts["slam_scans_rejected"] == 1
    # The scan in flight at the stop is no input of the run's filter: not recorded for a replay to feed.
    assert recorded.count("slam_scan") == 2
