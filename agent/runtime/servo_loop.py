"""The servo loop at ``control.loop_rate_hz``: wheel positions in -> odometry -> fusion; the velocity
command out (``DriveCommand``: its dead-man gives zero when the command is stale).

A silent servo is commanded zero (whatever still listens stops); when it answers again it is commanded
zero first and held there a moment (``control.recovery_hold_s``) whatever the command says.
"""

from __future__ import annotations

import contextlib
import logging
import time

from agent.fusion import PoseFilter
from agent.recording.messages import WheelCommandSample
from agent.runtime.health import Heartbeat
from agent.runtime.hotpath import HotPath
from agent.runtime.loop_state import LoopState
from agent.runtime.motion import DriveCommand, OdometryTrack, StillDetector, wheel_speeds
from drivers.errors import DeviceError
from drivers.samples import WheelState
from drivers.servos.base import WheelServos
from drivers.servos.odometry import WheelOdometry

__all__ = ["servo_loop"]

log = logging.getLogger(__name__)


def servo_loop(
    state: LoopState,
    beat: Heartbeat,
    *,
    servos: WheelServos,
    hot_path: HotPath,
    fusion: PoseFilter,
    drive: DriveCommand,
    still: StillDetector,
    odometry_track: OdometryTrack,
) -> None:
    watch = state.watch["servos"]
    cc = state.config.control
    period_s = 1.0 / cc.loop_rate_hz
    radius = float(getattr(servos, "wheel_radius_m", 0.0))
    track = float(getattr(servos, "track_m", 0.0))
    if not (radius > 0 and track > 0):
        raise DeviceError("the servo backend does not say its wheel radius and track", "servos")
    odometry = WheelOdometry(radius, track)
    previous: WheelState | None = None
    merged = False
    # Twice what the base can do, plus slack: beyond this an odometry interval's timing is wrong.
    max_ds_per_s = 2.0 * cc.max_speed_mps + 0.1
    max_dyaw_per_s = 2.0 * cc.max_turn_radps + 0.5
    t_next = time.monotonic()
    while not state.stop.is_set():
        beat.beat()
        if not state.open("servos", servos):
            previous = None
            state.retry_wait(beat, 1.0)
            continue
        hot_path.give_way()
        state.servo_read_since_ns = state.clock_ns()
        try:
            wheels = servos.read()
        except DeviceError as exc:
            state.servo_read_since_ns = 0
            watch.bad(f"silent: {exc}")
            previous = None
            merged = False
            # Whatever still listens stops; a silent servo keeps its last goal until it hears again.
            with contextlib.suppress(DeviceError):
                servos.set_velocity(0.0, 0.0)
            state.stop.wait(period_s)
            continue
        state.servo_read_since_ns = 0
        now = state.clock_ns()
        if watch.good():
            # Back from a fault: zero first, and hold zero a moment whatever the command says.
            drive.hold(now)
            state.count("servo_recoveries")
            try:
                servos.set_velocity(0.0, 0.0)
                state.count("zero_on_recovery")
                log.warning("servos answer again: zero velocity commanded")
            except DeviceError as exc:
                watch.bad(f"zero velocity after recovery failed: {exc}")
                continue
        state.hardware_error = wheels.hardware_error
        if any(wheels.hardware_error):
            state.count("servo_hardware_error_reads")
        deferred = False
        if previous is not None and wheels.host_time_ns > previous.host_time_ns:
            dl = wheels.position_rad[0] - previous.position_rad[0]
            dr = wheels.position_rad[1] - previous.position_rad[1]
            # ds = r (dphi_l + dphi_r) / 2, dyaw = r (dphi_r - dphi_l) / track
            ds = radius * (dl + dr) / 2.0
            dyaw = radius * (dr - dl) / track
            dt = (wheels.host_time_ns - previous.host_time_ns) * 1e-9
            if not merged and (abs(ds) > max_ds_per_s * dt or abs(dyaw) > max_dyaw_per_s * dt):
                # Faster than the base can go: the read's host time is earlier than when the servos
                # sampled (a reply that waited for a busy bus or CPU). The distance is right, the stamp
                # is not: leave this sample out and let the next interval span both.
                deferred = merged = True
                state.count("odometry_merged")
            else:
                merged = False
                fusion.add_odometry(previous.host_time_ns, wheels.host_time_ns, ds, dyaw, arrival_ns=now)
        elif previous is None and odometry.odom is not None:
            # A new reference after a fault: the odometry frame continues from where it was.
            last = odometry.odom
            odometry.reset(last.x_m, last.y_m, last.yaw_rad)
        odom = odometry.update(wheels)
        if previous is None:
            still.reset()
        still.update(wheels.host_time_ns, (odom.x_m, odom.y_m, odom.yaw_rad))
        odometry_track.add(wheels.host_time_ns, (odom.x_m, odom.y_m, odom.yaw_rad))
        if not deferred:
            previous = wheels
        state.count("wheel_reads")
        state.record("wheels", wheels.host_time_ns, wheels)
        command = drive.current(state.clock_ns())
        left, right = wheel_speeds(command.v_mps, command.omega_radps, radius, track)
        try:
            servos.set_velocity(left, right)
        except DeviceError as exc:
            watch.bad(f"velocity command failed: {exc}")
        else:
            if state.recording:
                sent_ns = state.clock_ns()
                sample = WheelCommandSample(sent_ns, left, right, command.v_mps, command.omega_radps)
                state.record("wheel_command", sent_ns, sample)
        t_next = state.wait_period(t_next, period_s)
