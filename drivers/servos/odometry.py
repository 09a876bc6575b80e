"""Wheel odometry for a differential-drive base: successive wheel angles -> pose and body velocity.

Pure: no I/O, no clock; time comes from the samples. Between two samples each wheel's rolled distance is
``s = r * dphi``; the base moves on a circular arc (exact when both wheels turn at constant speeds in the
interval), and the pose is advanced along that arc, not by a first-order Euler step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from drivers.samples import WheelState


@dataclass(frozen=True, slots=True)
class Odom:
    """Pose of the base in the odometry frame (x forward at start, y left, yaw counter-clockwise) and its
    body velocity, at the wheel sample's host time."""

    x_m: float
    y_m: float
    yaw_rad: float
    v_mps: float
    omega_radps: float
    host_time_ns: int
    distance_m: float = 0.0  # path length travelled by the base centre since the start


def _wrap(angle_rad: float) -> float:
    return math.atan2(math.sin(angle_rad), math.cos(angle_rad))


def _sinc(x: float) -> float:
    """sin(x)/x, with its Taylor series near 0 where the quotient loses precision."""
    if abs(x) < 1e-4:
        return 1.0 - x * x / 6.0
    return math.sin(x) / x


class WheelOdometry:
    """Integrates :class:`~drivers.samples.WheelState` samples (wheel angles, forward positive).

    Body velocity is the arc travelled divided by the time it took, over at least ``velocity_window_s``:
    polled faster than that, one sample moves a wheel by less than an encoder tick and a per-sample
    quotient would be mostly quantization. Until a window has passed the servos' own speed readings are
    used.

    The first sample only sets the reference angles. A sample whose time is not after the previous one
    (a clock step, samples out of order) still moves the pose, since wheel angles are absolute, but it
    restarts the velocity window; ``time_reversals`` counts such samples.
    """

    def __init__(
        self,
        wheel_radius_m: float,
        track_m: float,
        x_m: float = 0.0,
        y_m: float = 0.0,
        yaw_rad: float = 0.0,
        velocity_window_s: float = 0.05,
    ) -> None:
        if not (wheel_radius_m > 0 and track_m > 0):
            raise ValueError(f"wheel radius and track must be positive, got {wheel_radius_m}, {track_m}")
        if velocity_window_s < 0:
            raise ValueError(f"velocity window must not be negative, got {velocity_window_s}")
        self.wheel_radius_m = wheel_radius_m
        self.track_m = track_m
        self.velocity_window_ns = round(velocity_window_s * 1e9)
        self.time_reversals = 0
        self.reset(x_m, y_m, yaw_rad)

    def reset(self, x_m: float = 0.0, y_m: float = 0.0, yaw_rad: float = 0.0) -> None:
        """Start again from a pose; the next sample becomes the new reference."""
        self._x, self._y, self._yaw = float(x_m), float(y_m), _wrap(float(yaw_rad))
        self._distance_m = 0.0
        # Signed arc length and unwrapped heading change since the start, for the velocity window.
        self._arc_m = 0.0
        self._turn_rad = 0.0
        self._window: tuple[int, float, float] = (0, 0.0, 0.0)  # (time, arc, turn) where it began
        self._v_mps = 0.0
        self._omega_radps = 0.0
        self._last: WheelState | None = None
        self._odom: Odom | None = None

    @property
    def odom(self) -> Odom | None:
        """The latest estimate, None before the first sample."""
        return self._odom

    def _measured_velocity(self, state: WheelState) -> tuple[float, float]:
        # v = r (wl + wr) / 2,  omega = r (wr - wl) / track
        wl, wr = state.velocity_radps
        r = self.wheel_radius_m
        return r * (wl + wr) / 2.0, r * (wr - wl) / self.track_m

    def _restart_window(self, state: WheelState) -> None:
        self._window = (state.host_time_ns, self._arc_m, self._turn_rad)
        self._v_mps, self._omega_radps = self._measured_velocity(state)

    def update(self, state: WheelState) -> Odom:
        last = self._last
        self._last = state
        if last is None:
            self._restart_window(state)
        else:
            self._advance(last, state)
        self._odom = Odom(
            self._x, self._y, self._yaw, self._v_mps, self._omega_radps, state.host_time_ns, self._distance_m
        )
        return self._odom

    def _advance(self, last: WheelState, state: WheelState) -> None:
        r = self.wheel_radius_m
        ds_left = r * (state.position_rad[0] - last.position_rad[0])
        ds_right = r * (state.position_rad[1] - last.position_rad[1])
        # Arc of the base centre: ds = (sl + sr) / 2, dyaw = (sr - sl) / track.
        ds = (ds_left + ds_right) / 2.0
        dyaw = (ds_right - ds_left) / self.track_m
        # Exact arc: the chord has length ds * sinc(dyaw / 2) and points along the mean heading
        # yaw + dyaw / 2; the same as R (sin(yaw + dyaw) - sin yaw), R = ds / dyaw, without dividing by dyaw.
        chord = ds * _sinc(dyaw / 2.0)
        heading = self._yaw + dyaw / 2.0
        self._x += chord * math.cos(heading)
        self._y += chord * math.sin(heading)
        self._yaw = _wrap(self._yaw + dyaw)
        self._distance_m += abs(ds)
        self._arc_m += ds
        self._turn_rad += dyaw

        t0_ns, arc0_m, turn0_rad = self._window
        if state.host_time_ns <= last.host_time_ns:
            self.time_reversals += 1
            self._restart_window(state)
        elif state.host_time_ns - t0_ns >= self.velocity_window_ns:
            # v = (s(t) - s(t0)) / (t - t0),  omega = (yaw(t) - yaw(t0)) / (t - t0)
            dt_s = (state.host_time_ns - t0_ns) * 1e-9
            self._v_mps = (self._arc_m - arc0_m) / dt_s
            self._omega_radps = (self._turn_rad - turn0_rad) / dt_s
            self._window = (state.host_time_ns, self._arc_m, self._turn_rad)
