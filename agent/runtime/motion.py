"""Small stateful helpers of the runtime's loops: the odometry track, the motor dead-man, the IMU tilt.

* :class:`OdometryTrack`: recent wheel-odometry poses (odometry frame) by time, so the SLAM thread can ask
  where odometry put the base when a scan was taken.
* :class:`DriveCommand`: the latest velocity command with its time. The servo loop asks it what to send:
  the command while it is fresh, zero once it is older than the dead-man timeout, and zero for a hold time
  after a servo fault clears, whatever the command says (a servo that comes back from a brown-out must not
  lurch off on a command that was meant for before).
* :class:`TiltEstimator`: roll and pitch of the base from the accelerometer, learnt while it stands still.
* :class:`StillDetector`: whether odometry says the base has not moved for a while.
"""

from __future__ import annotations

import bisect
import collections
import logging
import math
import threading
from dataclasses import dataclass

from agent.runtime.types import Tilt

__all__ = ["DriveCommand", "OdometryTrack", "StillDetector", "TiltEstimator", "WheelCommand", "wheel_speeds"]

log = logging.getLogger(__name__)

Pose = tuple[float, float, float]


class OdometryTrack:
    """Odometry poses by host time (``keep_s`` of them), interpolated. Thread-safe."""

    def __init__(self, keep_s: float = 3.0, hold_s: float = 0.3) -> None:
        self.keep_ns = int(keep_s * 1e9)
        self.hold_ns = int(hold_s * 1e9)
        self._t: collections.deque[int] = collections.deque()
        self._poses: collections.deque[Pose] = collections.deque()
        self._lock = threading.Lock()

    def add(self, t_ns: int, pose: Pose) -> None:
        with self._lock:
            if self._t and t_ns <= self._t[-1]:
                return
            self._t.append(t_ns)
            self._poses.append(pose)
            while self._t and self._t[0] < t_ns - self.keep_ns:
                self._t.popleft()
                self._poses.popleft()

    def clear(self) -> None:
        with self._lock:
            self._t.clear()
            self._poses.clear()

    def at(self, t_ns: int) -> Pose | None:
        """The odometry pose at ``t_ns``: interpolated inside the track, extrapolated at the last speed for
        up to ``hold_s`` after it; None outside that."""
        with self._lock:
            if not self._t:
                return None
            times = self._t
            if t_ns >= times[-1]:
                if t_ns - times[-1] > self.hold_ns:
                    return None
                if len(times) < 2:
                    return self._poses[-1]
                i = len(times) - 1
            elif t_ns < times[0]:
                return None
            else:
                i = max(bisect.bisect_right(times, t_ns), 1)
            t0, t1 = times[i - 1], times[i]
            (x0, y0, a0), (x1, y1, a1) = self._poses[i - 1], self._poses[i]
            w = (t_ns - t0) / (t1 - t0) if t1 > t0 else 0.0
            da = math.remainder(a1 - a0, math.tau)
            return (x0 + w * (x1 - x0), y0 + w * (y1 - y0), math.remainder(a0 + w * da, math.tau))


@dataclass(frozen=True, slots=True)
class WheelCommand:
    v_mps: float
    omega_radps: float
    reason: str  # "command", "stale" (dead-man), "hold" (after a fault), "none" (nothing commanded yet)


def wheel_speeds(
    v_mps: float, omega_radps: float, wheel_radius_m: float, track_m: float
) -> tuple[float, float]:
    """(left, right) wheel speeds in rad/s: v_l = v - omega track / 2, v_r = v + omega track / 2."""
    half = omega_radps * track_m / 2.0
    return (v_mps - half) / wheel_radius_m, (v_mps + half) / wheel_radius_m


class DriveCommand:
    """The dead-man between whoever commands the base and the servo loop. Thread-safe."""

    def __init__(
        self, deadman_timeout_s: float, recovery_hold_s: float, max_speed_mps: float, max_turn_radps: float
    ) -> None:
        self.timeout_ns = int(deadman_timeout_s * 1e9)
        self.hold_ns = int(recovery_hold_s * 1e9)
        self.max_speed_mps = max_speed_mps
        self.max_turn_radps = max_turn_radps
        self._lock = threading.Lock()
        self._command: tuple[float, float, int] | None = None
        self._hold_until_ns = 0
        self._stale_logged = False
        self.commands = 0
        self.clamped = 0
        self.stale_events = 0

    def set(self, v_mps: float, omega_radps: float, now_ns: int) -> None:
        if not (math.isfinite(v_mps) and math.isfinite(omega_radps)):
            raise ValueError(f"velocity command must be finite, got ({v_mps}, {omega_radps})")
        v = max(-self.max_speed_mps, min(self.max_speed_mps, v_mps))
        w = max(-self.max_turn_radps, min(self.max_turn_radps, omega_radps))
        with self._lock:
            if (v, w) != (v_mps, omega_radps):
                self.clamped += 1
            self._command = (v, w, now_ns)
            self.commands += 1

    def hold(self, now_ns: int) -> None:
        """Zero for the recovery hold from now on, and forget the command given before."""
        with self._lock:
            self._hold_until_ns = now_ns + self.hold_ns
            self._command = None

    def current(self, now_ns: int) -> WheelCommand:
        with self._lock:
            if now_ns < self._hold_until_ns:
                return WheelCommand(0.0, 0.0, "hold")
            if self._command is None:
                return WheelCommand(0.0, 0.0, "none")
            v, w, t = self._command
            if now_ns - t > self.timeout_ns:
                if not self._stale_logged:
                    self._stale_logged = True
                    self.stale_events += 1
                    log.warning(
                        "velocity command is %.2f s old: dead-man, commanding zero", (now_ns - t) * 1e-9
                    )
                return WheelCommand(0.0, 0.0, "stale")
            self._stale_logged = False
            return WheelCommand(v, w, "command")


class TiltEstimator:
    """Roll and pitch of the base from the accelerometer, learnt while the base stands still.

    At rest the specific force is gravity alone, f = g (-sin pitch, sin roll cos pitch, cos roll cos pitch),
    so roll = atan2(f_y, f_z) and pitch = atan2(-f_x, sqrt(f_y^2 + f_z^2)). Moving, the base's own
    acceleration adds to it, and odometry does not know that acceleration to the 1 cm/s^2 that is already
    0.06 deg of tilt (3 mm of VLP error under a 2.6 m ceiling): so the caller feeds samples only while
    odometry says the base is still. The estimate starts level (the floor is, mostly) and follows the
    still samples through a first-order low pass with time constant ``tau_s``.
    """

    def __init__(self, tau_s: float = 1.0) -> None:
        self.tau_s = tau_s
        self._lock = threading.Lock()
        self._roll = 0.0
        self._pitch = 0.0
        self._last_ns: int | None = None
        self.samples = 0

    def update(self, t_ns: int, accel_mps2: tuple[float, float, float]) -> None:
        """One accelerometer sample taken while the base was still."""
        fx, fy, fz = accel_mps2
        if fz <= 0:
            return  # upside down or in free fall: not a tilt
        roll = math.atan2(fy, fz)
        pitch = math.atan2(-fx, math.hypot(fy, fz))
        with self._lock:
            # k = dt / (tau + dt), dt capped so that the first sample after a drive is one step, not a jump.
            dt = 0.01 if self._last_ns is None else min(max((t_ns - self._last_ns) * 1e-9, 0.0), 0.02)
            k = dt / (self.tau_s + dt) if self.tau_s > 0 else 1.0
            self._roll += k * (roll - self._roll)
            self._pitch += k * (pitch - self._pitch)
            self._last_ns = t_ns
            self.samples += 1

    def tilt(self) -> Tilt:
        with self._lock:
            return Tilt(self._roll, self._pitch)


class StillDetector:
    """Still since when, by odometry: the base's position moved less than ``tolerance_m`` and its heading
    less than ``tolerance_rad`` over the last ``hold_s``. Thread-safe to read."""

    def __init__(self, hold_s: float = 0.5, tolerance_m: float = 0.001, tolerance_rad: float = 0.002) -> None:
        self.hold_ns = int(hold_s * 1e9)
        self.tolerance_m = tolerance_m
        self.tolerance_rad = tolerance_rad
        self._anchor: tuple[int, float, float, float] | None = None
        self._last_ns = 0

    def update(self, t_ns: int, pose: Pose) -> None:
        anchor = self._anchor
        if anchor is None or (
            math.hypot(pose[0] - anchor[1], pose[1] - anchor[2]) > self.tolerance_m
            or abs(math.remainder(pose[2] - anchor[3], math.tau)) > self.tolerance_rad
        ):
            self._anchor = (t_ns, pose[0], pose[1], pose[2])
        self._last_ns = t_ns

    def reset(self) -> None:
        self._anchor = None

    def still_at(self, t_ns: int, max_age_ns: int) -> bool:
        """Still at ``t_ns``: still for ``hold_s``, and the last odometry at most ``max_age_ns`` old."""
        anchor = self._anchor
        if anchor is None or t_ns - self._last_ns > max_age_ns:
            return False
        return self._last_ns - anchor[0] >= self.hold_ns
