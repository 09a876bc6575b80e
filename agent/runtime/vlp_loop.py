"""The hot path's loop: the newest frame -> VLP fix (with the fused pose as its prior) -> fusion -> pose
bytes written; a fused fix also goes to SLAM now and then.

It runs the garbage collector between frames once the agent has settled its heap
(``agent.runtime.collector``), and may run under real-time scheduling (``agent.runtime.priority``).
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable

import numpy as np

from agent.config import VlpConfig
from agent.fusion import FixIntegrity, PoseFilter, Source
from agent.runtime.collector import IdleCollector
from agent.runtime.health import Heartbeat
from agent.runtime.hotpath import HotPath
from agent.runtime.localizer import FrameLocalizer
from agent.runtime.loop_state import LoopState
from agent.runtime.mailbox import BoundedQueue, LatestMailbox, MailboxClosed
from agent.runtime.motion import TiltEstimator
from agent.runtime.types import AbsoluteFix, NoFix, Prior
from drivers.samples import Frame

__all__ = ["VlpLoop", "vlp_covariance", "vlp_prior"]

log = logging.getLogger(__name__)

# A VLP prior is never tighter than this: the filter may be confident and wrong.
_MIN_PRIOR_SIGMA_XY_M = 0.05
_MIN_PRIOR_SIGMA_YAW_RAD = math.radians(3.0)
# At most one VLP fix per this interval goes to SLAM: the filter multiplies every fix it is given into its
# weights at the next update, and thirty nearly identical fixes would count as thirty independent ones.
_SLAM_FIX_INTERVAL_NS = 500_000_000


def vlp_prior(fusion: PoseFilter, t_ns: int) -> Prior:
    """Where the fused pose puts the base at ``t_ns``, never more confidently than the floors above."""
    est = fusion.estimate_at(t_ns)
    c, s = math.cos(est.yaw_rad), math.sin(est.yaw_rad)
    return Prior(
        est.x_m,
        est.y_m,
        est.yaw_rad,
        max(est.sigma_xy_m, _MIN_PRIOR_SIGMA_XY_M),
        max(est.sigma_yaw_rad, _MIN_PRIOR_SIGMA_YAW_RAD),
        est.v_mps * c,
        est.v_mps * s,
        est.omega_radps,
    )


def vlp_covariance(fix: AbsoluteFix, vc: VlpConfig) -> np.ndarray:
    """The fix's covariance plus the floor the config sets for what it leaves out (the LED survey's and
    the calibration's errors, the same for every frame under the same LEDs)."""
    cov = np.array(fix.covariance, dtype=np.float64)
    cov[0, 0] += vc.sigma_floor_m**2
    cov[1, 1] += vc.sigma_floor_m**2
    if fix.yaw_rad is not None and cov.shape[0] == 3:
        cov[2, 2] += vc.sigma_floor_yaw_rad**2
    return cov


class VlpLoop:
    """The hot path. ``tilt``: None without an IMU; ``slam_fixes``: None without SLAM; ``publish(trigger_ns,
    arrival_ns)`` writes the fused pose."""

    def __init__(
        self,
        state: LoopState,
        *,
        localizer: FrameLocalizer | None,
        fusion: PoseFilter,
        frames: LatestMailbox[tuple[Frame, int]],
        hot_path: HotPath,
        collector: IdleCollector,
        tilt: TiltEstimator | None,
        slam_fixes: BoundedQueue[AbsoluteFix] | None,
        publish: Callable[[int | None, int | None], None],
    ) -> None:
        self.state = state
        self.localizer = localizer
        self.fusion = fusion
        self.frames = frames
        self.hot_path = hot_path
        self.collector = collector
        self.tilt = tilt
        self.slam_fixes = slam_fixes
        self.publish = publish
        self._last_slam_fix_ns = 0

    def run(self, beat: Heartbeat) -> None:
        state = self.state
        state.realtime("hot_path")
        while not state.stop.is_set():
            beat.beat()
            item = self.frames.take(0.25)
            if item is None or self.localizer is None:
                self.hot_path.settle()
                self.collector.collect_if_due()
                continue
            with self.hot_path.busy():
                c0 = time.thread_time()
                try:
                    self.locate(*item)
                finally:
                    state.hot_cpu_ms.add(1e3 * (time.thread_time() - c0))
            # The pose is written: the garbage of this frame (and of every other thread) goes now.
            self.collector.collect_if_due()

    def locate(self, frame: Frame, arrival_ns: int) -> None:
        """The hot path: frame -> fix -> fusion -> pose bytes written."""
        state = self.state
        t = frame.host_time_ns
        tilt = self.tilt.tilt() if self.tilt is not None else None
        assert self.localizer is not None
        t0 = time.perf_counter()
        result = self.localizer.process(frame, tilt, vlp_prior(self.fusion, t))
        elapsed_ms = 1e3 * (time.perf_counter() - t0)
        state.vlp_ms.add(elapsed_ms)
        with state.counts_lock:
            if isinstance(result, NoFix):
                state.no_fix[result.reason] += 1
                state.counts["no_fix"] += 1
            else:
                state.counts["fixes"] += 1
        state.record("no_fix" if isinstance(result, NoFix) else "vlp_fix", result.t_ns, result)
        if isinstance(result, NoFix):
            return
        fused = self.fusion.add_pose(
            Source.VLP,
            result.t_ns,
            result.x_m,
            result.y_m,
            result.yaw_rad,
            vlp_covariance(result, state.config.vlp),
            arrival_ns=state.clock_ns(),
            relocalize=True,
            integrity=FixIntegrity(result.degraded, result.protection_level_m),
        )
        if fused.relocalized:
            log.warning("fusion relocalized on VLP (reset counter %d)", self.fusion.reset_counter)
            state.count("relocalizations")
        if not fused.accepted:
            # Refused for integrity (a degraded fix, or one past the alert limit, the prediction could not
            # vouch for), or gated out (a nominal fix that disagrees with the fused pose).
            state.count(f"fixes_rejected_{fused.refused}" if fused.refused else "fixes_rejected")
            return
        state.count("fixes_fused")
        if fused.guarded:
            state.count("fixes_fused_guarded")  # of fixes_fused: degraded or past the alert limit
        self.publish(t, arrival_ns)
        if self.slam_fixes is not None and t - self._last_slam_fix_ns >= _SLAM_FIX_INTERVAL_NS:
            self._last_slam_fix_ns = t
            with contextlib.suppress(MailboxClosed):
                self.slam_fixes.put(result)
