"""The IMU loop at 100 Hz: gyro yaw rate -> fusion; the accelerometer -> the base's tilt for VLP, learnt
only while the wheels' odometry says the base stands still."""

from __future__ import annotations

import time

from agent.fusion import PoseFilter
from agent.runtime.health import Heartbeat
from agent.runtime.hotpath import HotPath
from agent.runtime.loop_state import LoopState
from agent.runtime.motion import StillDetector, TiltEstimator
from drivers.errors import DeviceError
from drivers.imu.base import Imu

__all__ = ["imu_loop"]

IMU_PERIOD_S = 0.01
# The IMU tilt is only learnt while odometry this recent says the base stands still.
_TILT_ODOMETRY_AGE_NS = 60_000_000


def imu_loop(
    state: LoopState,
    beat: Heartbeat,
    *,
    imu: Imu,
    hot_path: HotPath,
    fusion: PoseFilter,
    still: StillDetector,
    tilt: TiltEstimator,
) -> None:
    watch = state.watch["imu"]
    t_next = time.monotonic()
    while not state.stop.is_set():
        beat.beat()
        if not state.open("imu", imu):
            state.retry_wait(beat, 1.0)
            continue
        hot_path.give_way()
        try:
            sample = imu.read()
        except DeviceError as exc:
            watch.bad(f"failed: {exc}")
            state.retry_wait(beat, 0.1)
            continue
        watch.good()
        state.count("imu_samples")
        state.record("imu", sample.host_time_ns, sample)
        now = state.clock_ns()
        fusion.add_gyro(sample.host_time_ns, sample.gyro_radps[2], arrival_ns=now)
        if still.still_at(sample.host_time_ns, _TILT_ODOMETRY_AGE_NS):
            # Only a base that stands still feels gravity alone (see TiltEstimator).
            tilt.update(sample.host_time_ns, sample.accel_mps2)
        t_next = state.wait_period(t_next, IMU_PERIOD_S)
