"""The SLAM loop: each queued scan, with the odometry at its time, through the laser localizer
(``agent.runtime.mapper``); the pose of each filter update that matched goes to the fusion.

It gives way to the hot path before each scan, and hands the localizer the VLP fixes the hot path queued
(at most one every half second, ``agent.runtime.vlp_loop``).

Three want the map out of the localizer, each on its own period: the navigation's static layer
(``map_period_s``, after a scan), the flight recorder's ``/map`` (``recorder.map_period_s``, after a scan)
and the saver (``agent.runtime.map_saver``: every interval, less its lead, or on request). With a SLAM
process each fetch is a round trip and a copy of the grid, so the loop fetches once, between two scans,
and hands that one image to every one of them that is due. It waits for a scan no longer than until the
saver is due, so a save starts on time (the saver's bound) rather than at the next scan.
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

_SCAN_WAIT_S = 0.25


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

    def _wait_s(self) -> float:
        """How long to wait for a scan: a quarter second, or until a save is due."""
        until = self.saver.seconds_until_due() if self.saver is not None else None
        return _SCAN_WAIT_S if until is None else min(_SCAN_WAIT_S, until)

    def run(self, beat: Heartbeat) -> None:
        state = self.state
        mapper = self.mapper
        while not state.stop.is_set():
            beat.beat()
            scan = self.scans.get(self._wait_s())
            if mapper is None:
                continue
            mapped = scan is not None and self._map_scan(mapper, scan)
            if state.stop.is_set():
                # Stopping: no fetch now (a SLAM process is then answering only the final save, and this
                # thread would wait on it past its join); the command's final save comes after the stop.
                break
            self._share_map(mapper, mapped)

    def _map_scan(self, mapper: ScanMapper, scan: Scan) -> bool:
        """The fixes queued, then the scan, through the mapper; its pose to the fusion. False: no odometry
        for the scan (not mapped)."""
        state = self.state
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
            return False
        step = mapper.update(scan, odom)
        # What SLAM took and with which odometry, for a replay (agent.recording.slam_replay). Not the scan
        # in flight when the agent stopped: the filter never took it or left its update unfinished, and a
        # replay fed it would make an update the run did not.
        restarts = getattr(mapper, "restarts", 0)  # a SLAM process restarted: a new map from here
        if not step.stopped:
            state.record("slam_scan", scan.host_time_ns, SlamScanSample(scan, odom, step.kind, restarts))
        # slam_scans_updated / _skipped / _rejected: what the mapper did with the scan. Not slam_rejected,
        # which counts the SLAM poses the fusion turned down (slam_fused + slam_rejected = the poses handed
        # to it, as recorded on /slam/pose): a scan the mapper rejected, or the one in flight at a stop, has
        # no pose.
        state.count(f"slam_scans_{step.kind}")
        if step.kind == "updated":
            if step.fix is None:
                state.slam_good = False
                return True
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
        return True

    def _share_map(self, mapper: ScanMapper, mapped: bool) -> None:
        """One fetch of the map for whoever is due: the navigation and the recorder after a scan was
        mapped (the map changed), the saver when its time is up or a save was asked for."""
        state, saver = self.state, self.saver
        now = state.clock_ns()
        to_navigation = mapped and self.on_map is not None and now - self._map_sent_ns >= self.map_period_ns
        record_period_s = state.config.recorder.map_period_s
        to_recorder = (
            mapped
            and state.recording
            and record_period_s > 0
            and now - self._map_recorded_ns >= record_period_s * 1e9
        )
        to_saver = saver is not None and saver.due()
        if to_saver and saver is not None and mapper.counters().get("filter_updates", 0) == 0:
            # Before the first filter update the "map" is one scan at a guessed pose: not worth a save.
            saver.skip()
            to_saver = False
        if not (to_navigation or to_recorder or to_saver):
            return
        content_s = saver.clock_s() if saver is not None else 0.0
        t0 = time.perf_counter()
        image = mapper.map_image()
        fetch_s = time.perf_counter() - t0
        state.count("map_fetches")
        if image is None:
            if to_saver and saver is not None:
                saver.skip()
            return
        if to_navigation and self.on_map is not None:
            self._map_sent_ns = now
            self.on_map(image)
            state.count("maps_to_navigation")
        if to_recorder:
            self._map_recorded_ns = now
            state.record("map", now, (now, image))
        if to_saver and saver is not None:
            saver.submit(image, fetch_s, content_s)
            state.count("map_saves_handed_over")
