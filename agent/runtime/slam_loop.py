"""The SLAM loop: each queued scan, with the odometry at its time, through the laser localizer
(``agent.runtime.mapper``); the pose of each filter update that matched goes to the fusion.

It gives way to the hot path before each scan, and hands the localizer the VLP fixes the hot path queued
(at most one every half second, ``agent.runtime.vlp_loop``). When a save of the map is due
(``agent.runtime.map_saver``), it takes the map out of the localizer between two scans and hands it to the
saver's thread, which writes it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from agent.fusion import PoseFilter, Source
from agent.recording.messages import SlamFixSample, SlamScanSample
from agent.runtime.health import Heartbeat
from agent.runtime.hotpath import HotPath
from agent.runtime.loop_state import LoopState
from agent.runtime.mailbox import BoundedQueue
from agent.runtime.map_saver import MapSaver
from agent.runtime.mapper import Pose, ScanMapper
from agent.runtime.motion import OdometryTrack
from agent.runtime.types import AbsoluteFix
from drivers.samples import Scan

__all__ = ["SlamLoop"]


class SlamLoop:
    """``odometry_track``: the wheels' odometry (None without wheels: the fused pose is the motion guess)."""

    def __init__(
        self,
        state: LoopState,
        *,
        mapper: ScanMapper | None,
        fusion: PoseFilter,
        scans: BoundedQueue[Scan],
        slam_fixes: BoundedQueue[AbsoluteFix],
        hot_path: HotPath,
        odometry_track: OdometryTrack | None,
        on_map: Callable[[Any], None] | None = None,
        map_period_s: float = 2.0,
        saver: MapSaver | None = None,
    ) -> None:
        self.state = state
        self.mapper = mapper
        self.fusion = fusion
        self.scans = scans
        self.slam_fixes = slam_fixes
        self.hot_path = hot_path
        self.odometry_track = odometry_track
        self.on_map = on_map  # the navigation's static layer: the map every map_period_s
        self.map_period_ns = int(map_period_s * 1e9)
        self._map_sent_ns = 0
        self._map_recorded_ns = 0
        self.saver = saver  # the map saved as the robot goes (None: only at the end, by the command)

    def odometry_at(self, t_ns: int) -> Pose | None:
        if self.odometry_track is not None:
            return self.odometry_track.at(t_ns)
        est = self.fusion.estimate_at(t_ns)  # no wheels: the fused pose is the best motion guess
        return (est.x_m, est.y_m, est.yaw_rad)

    def _record_map(self) -> None:
        """A map snapshot for the flight recorder every ``recorder.map_period_s`` (0: none)."""
        state, mapper = self.state, self.mapper
        period_s = state.config.recorder.map_period_s
        if not state.recording or not period_s or mapper is None:
            return
        now = state.clock_ns()
        if now - self._map_recorded_ns < period_s * 1e9:
            return
        image = mapper.map_image()
        if image is not None:
            self._map_recorded_ns = now
            state.record("map", now, (now, image))

    def run(self, beat: Heartbeat) -> None:
        state = self.state
        mapper = self.mapper
        while not state.stop.is_set():
            beat.beat()
            scan = self.scans.get(0.25)
            if mapper is not None and self.saver is not None and self.saver.due():
                self._hand_over_map(mapper, self.saver)
            if scan is None or mapper is None:
                continue
            self.hot_path.give_way()
            for fix in self.slam_fixes.drain():
                odom = self.odometry_at(fix.t_ns)
                if odom is not None:
                    mapper.add_fix(fix, odom)
                    restarts = getattr(mapper, "restarts", 0)
                    state.record("slam_fix", fix.t_ns, SlamFixSample(fix, odom, restarts))
            odom = self.odometry_at(scan.host_time_ns)
            if odom is None:
                state.count("slam_scans_without_odometry")
                continue
            step = mapper.update(scan, odom)
            # What SLAM took and with which odometry, for a replay (agent.recording.slam_replay).
            restarts = getattr(mapper, "restarts", 0)  # a SLAM process restarted: a new map from here
            state.record("slam_scan", scan.host_time_ns, SlamScanSample(scan, odom, step.kind, restarts))
            state.count(f"slam_{step.kind}")
            if self.on_map is not None and state.clock_ns() - self._map_sent_ns >= self.map_period_ns:
                image = mapper.map_image()
                if image is not None:
                    self._map_sent_ns = state.clock_ns()
                    self.on_map(image)
                    state.count("maps_to_navigation")
            self._record_map()
            if step.kind == "updated":
                if step.fix is None:
                    state.slam_good = False
                    continue
                fix = step.fix
                state.record("slam_pose", fix.t_ns, fix)
                result = self.fusion.add_pose(
                    Source.SLAM,
                    fix.t_ns,
                    fix.x_m,
                    fix.y_m,
                    fix.yaw_rad,
                    fix.covariance,
                    arrival_ns=state.clock_ns(),
                )
                state.slam_good = result.accepted
                state.count("slam_fused" if result.accepted else "slam_rejected")

    def _hand_over_map(self, mapper: ScanMapper, saver: MapSaver) -> None:
        # Before the first filter update the "map" is one scan at a guessed pose: not worth a save.
        t0 = time.perf_counter()
        image = mapper.map_image() if mapper.counters().get("filter_updates", 0) > 0 else None
        if image is None:
            saver.skip()
            return
        saver.submit(image, time.perf_counter() - t0)
        self.state.count("map_saves_handed_over")
