"""What the filter is fed: the laser's fixed geometry, and the gate that turns away bad scans.

Range convention everywhere in ``agent.slam``: ``ranges_m`` is float64, one value per beam, and a value
below ``min_range_m`` (0 included) or at/above ``no_return_m`` means "no return" (nothing was hit within
the sensor's reach; URG error codes and SICK saturation values end up here). NaN or infinite values are
not a convention but corruption, and reject the whole scan.
"""

from __future__ import annotations

import enum
import logging
import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from agent.slam.pose import between
from drivers.samples import Scan

FloatArray = npt.NDArray[np.float64]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LaserGeometry:
    """Beam angles in the laser frame (counter-clockwise, 0 straight ahead), the sensor's valid range
    interval, and where the laser sits on the robot base (``mount``: x_m forward, y_m left, yaw_rad)."""

    angles_rad: FloatArray
    min_range_m: float
    no_return_m: float
    mount: tuple[float, float, float] = (0.0, 0.0, 0.0)
    beam_time_s: FloatArray | None = None  # when each beam is measured, relative to the scan's timestamp

    def __post_init__(self) -> None:
        if self.angles_rad.ndim != 1 or self.angles_rad.size < 2:
            raise ValueError(
                f"angles_rad must be a 1-D array of at least 2 beams, got {self.angles_rad.shape}"
            )
        if not 0.0 <= self.min_range_m < self.no_return_m:
            raise ValueError(
                f"need 0 <= min_range_m < no_return_m, got {self.min_range_m}, {self.no_return_m}"
            )

    @property
    def beams(self) -> int:
        return int(self.angles_rad.size)

    @classmethod
    def urg04lx(
        cls, mount: tuple[float, float, float] = (0.0, 0.0, 0.0), sweep_start_s: float = 0.0
    ) -> LaserGeometry:
        """Hokuyo URG-04LX: steps 44..725 of 1024 per turn, front step 384 (682 beams over 240 deg)."""
        steps = np.arange(44, 726, dtype=np.float64)
        # 600 rpm, 1024 steps per turn: one step every 97.7 us; the scan's time is its first beam's.
        beam_time_s = (steps - 44.0) * (0.1 / 1024.0) + sweep_start_s
        return cls((steps - 384.0) * (2.0 * math.pi / 1024.0), 0.02, 5.6, mount, beam_time_s)

    @classmethod
    def from_scan(cls, scan: Scan, mount: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> LaserGeometry:
        """The geometry of scans from the laser driver (``drivers.samples.Scan``)."""
        return cls(scan.angles_rad(), scan.min_range_mm / 1000.0, (scan.max_range_mm + 1) / 1000.0, mount)


def ranges_from_scan(scan: Scan) -> FloatArray:
    """A driver ``Scan`` in this package's range convention: error codes (below min range) become 0."""
    ranges_m: FloatArray = scan.ranges_mm.astype(np.float64) / 1000.0
    ranges_m[~scan.valid_mask()] = 0.0
    return ranges_m


class Rejection(enum.StrEnum):
    """Why a scan was turned away. The filter counts each and carries on with the next scan."""

    NO_RETURNS = "no_returns"  # all zero / every beam out of range: nothing to match or map
    NON_FINITE = "non_finite"  # NaN or inf in the ranges: corrupt data
    BEAM_COUNT = "beam_count"  # not the configured number of beams: another sensor mode or a cut frame
    TIME_BACKWARDS = "time_backwards"  # timestamp not after the last accepted scan's
    POSE_JUMP = "pose_jump"  # odometry moved faster than the robot can between two scans


@dataclass
class ScanGate:
    """Checks each incoming scan against the laser geometry and the last accepted scan.

    A pose jump is odometry between two accepted scans that implies more than ``max_speed_mps`` /
    ``max_turn_radps`` (plus a fixed slack for timestamp jitter); the gate then re-anchors its odometry
    reference so that the jump is not applied as motion (the caller is told through the rejection).
    """

    geometry: LaserGeometry
    min_returns: int = 10
    max_speed_mps: float = 2.0
    max_turn_radps: float = 4.0
    slack_m: float = 0.5
    slack_rad: float = 1.0
    counts: Counter[Rejection] = field(default_factory=Counter)
    last_t_s: float | None = None
    last_odom: FloatArray | None = None
    previous_t_s: float | None = None  # last_t_s before the latest check

    def check(self, t_s: float, ranges_m: FloatArray, odom_pose: FloatArray) -> Rejection | None:
        """None if the scan may be used; otherwise the reason, counted in ``counts``."""
        self.previous_t_s = self.last_t_s
        reason = self._reason(t_s, ranges_m, odom_pose)
        if reason is None:
            self.last_t_s = t_s
            self.last_odom = np.array(odom_pose, dtype=np.float64)
        else:
            self.counts[reason] += 1
            log.debug("scan at t=%.3f s rejected: %s", t_s, reason.value)
            if reason is Rejection.POSE_JUMP:
                self.last_t_s = t_s
                self.last_odom = np.array(odom_pose, dtype=np.float64)
        return reason

    def _reason(self, t_s: float, ranges_m: FloatArray, odom_pose: FloatArray) -> Rejection | None:
        if ranges_m.shape != (self.geometry.beams,):
            return Rejection.BEAM_COUNT
        if not (np.all(np.isfinite(ranges_m)) and np.all(np.isfinite(odom_pose)) and math.isfinite(t_s)):
            return Rejection.NON_FINITE
        returns = np.count_nonzero(
            (ranges_m >= self.geometry.min_range_m) & (ranges_m < self.geometry.no_return_m)
        )
        if returns < self.min_returns:
            return Rejection.NO_RETURNS
        if self.last_t_s is not None and t_s <= self.last_t_s:
            return Rejection.TIME_BACKWARDS
        if self.last_odom is not None and self.last_t_s is not None:
            dt_s = t_s - self.last_t_s
            step = between(self.last_odom, odom_pose)
            if (
                math.hypot(step[0], step[1]) > self.max_speed_mps * dt_s + self.slack_m
                or abs(step[2]) > self.max_turn_radps * dt_s + self.slack_rad
            ):
                return Rejection.POSE_JUMP
        return None
