"""Where the followed person is, in the map frame, with a covariance: a laser person detector fused over
time by a constant-velocity Kalman filter (``docs/following.md``, "The person's position").

* :func:`detect_people`: the scan is cut into clusters where consecutive returns jump apart; a cluster of a
  person's width (``min_width_m``-``max_width_m`` end to end, at least ``min_points`` returns) whose
  returns are mostly *not* on the static map's occupied cells is a candidate. Its centre is the returns'
  mean pushed ``centre_offset_m`` further along the ray (the laser sees the near surface of a body).
* :class:`PersonTracker`: one person, a constant-velocity Kalman filter over (x, y, vx, vy) with white
  acceleration noise. :meth:`PersonTracker.acquire` starts a track on the candidate nearest the robot
  inside a bearing window (the RFID prior, ``coarse.within``); :meth:`PersonTracker.update_detections`
  keeps the identity by gating (the candidate with the smallest Mahalanobis distance inside the chi-square
  gate, none outside it); :meth:`PersonTracker.update_bearing` takes a bearing from the robot (the forward
  camera's tracker, ``agent.runtime.follow_loop``) as a second measurement, an extended Kalman update
  gated likewise. With no accepted measurement for ``lost_after_s`` up to the last look (scan) the track
  is dropped (lost).

Pure: numpy in, estimates out, time passed in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = [
    "DetectorConfig",
    "PersonDetections",
    "PersonEstimate",
    "PersonTracker",
    "TrackerConfig",
    "detect_people",
]

FloatArray = npt.NDArray[np.float64]
Pose = tuple[float, float, float]

GATE_CHI2_2DOF = 11.83  # 99.73 % (3 sigma) of a 2-D Gaussian
GATE_CHI2_1DOF = 9.0  # 3 sigma


@dataclass(frozen=True, slots=True)
class DetectorConfig:
    min_width_m: float = 0.1
    max_width_m: float = 0.6
    min_points: int = 3
    jump_m: float = 0.12  # consecutive returns further apart than this (or 3 beam spacings) split clusters
    static_fraction: float = 0.5  # a cluster with more of its returns on static occupied cells is the map
    centre_offset_m: float = 0.15  # from the returns' mean to the centre of a 0.2 m round body, along the ray
    max_range_m: float = 5.0


@dataclass(frozen=True, slots=True)
class PersonDetections:
    """Candidates in the map frame: ``centres`` (n, 2), their ``widths_m`` (n,)."""

    centres: FloatArray
    widths_m: FloatArray

    def __len__(self) -> int:
        return len(self.centres)


def detect_people(
    angles_rad: FloatArray,
    ranges_m: FloatArray,
    laser_pose: Pose,
    static: npt.NDArray[np.bool_] | None = None,
    config: DetectorConfig = DetectorConfig(),
) -> PersonDetections:
    """Person-sized clusters in one scan. ``angles_rad``/``ranges_m``: the beams in the laser's frame
    (non-finite or non-positive range: no return); ``laser_pose``: the laser in the map frame; ``static``:
    per beam, whether its return lies on the static map's occupied cells (None: no map, nothing is
    static)."""
    angles = np.asarray(angles_rad, dtype=np.float64)
    ranges = np.asarray(ranges_m, dtype=np.float64)
    valid = np.isfinite(ranges) & (ranges > 0.0) & (ranges <= config.max_range_m)
    lx, ly, lyaw = laser_pose
    theta = angles + lyaw
    px = lx + ranges * np.cos(theta)
    py = ly + ranges * np.sin(theta)
    on_map = np.zeros(len(ranges), dtype=bool) if static is None else np.asarray(static, dtype=bool)
    step = float(np.median(np.abs(np.diff(angles)))) if len(angles) > 1 else 0.0
    centres: list[tuple[float, float]] = []
    widths: list[float] = []
    idx = np.flatnonzero(valid)
    if len(idx) == 0:
        return PersonDetections(np.zeros((0, 2)), np.zeros(0))
    # Split where a beam is missing or consecutive returns are far apart.
    gap = np.hypot(np.diff(px[idx]), np.diff(py[idx]))
    allowed = np.maximum(config.jump_m, 3.0 * step * np.minimum(ranges[idx][1:], ranges[idx][:-1]))
    cut = (np.diff(idx) > 1) | (gap > allowed)
    starts = np.concatenate([[0], np.flatnonzero(cut) + 1])
    ends = np.concatenate([np.flatnonzero(cut) + 1, [len(idx)]])
    for a, b in zip(starts, ends, strict=True):
        members = idx[a:b]
        if len(members) < config.min_points:
            continue
        width = math.hypot(px[members[-1]] - px[members[0]], py[members[-1]] - py[members[0]])
        if not config.min_width_m <= width <= config.max_width_m:
            continue
        if np.mean(on_map[members]) > config.static_fraction:
            continue
        cx, cy = float(np.mean(px[members])), float(np.mean(py[members]))
        ray = math.atan2(cy - ly, cx - lx)
        centres.append(
            (cx + config.centre_offset_m * math.cos(ray), cy + config.centre_offset_m * math.sin(ray))
        )
        widths.append(width)
    if not centres:
        return PersonDetections(np.zeros((0, 2)), np.zeros(0))
    return PersonDetections(np.array(centres, dtype=np.float64), np.array(widths, dtype=np.float64))


@dataclass(frozen=True, slots=True)
class TrackerConfig:
    accel_sd_mps2: float = 2.0  # white acceleration noise of the constant-velocity model
    position_sd_m: float = 0.08  # a laser detection's centre, per axis
    initial_speed_sd_mps: float = 1.0
    lost_after_s: float = 1.0  # no accepted measurement for this long: the track is dropped
    max_acquire_range_m: float = 4.5  # the coarse layer's grid ends here
    reacquire_s: float = 5.0  # after a loss, only candidates near where the lost track would be by now
    reacquire_m: float = 1.0  # ... within this of it (plus 0.5 m per second since the loss)


@dataclass(frozen=True, slots=True)
class PersonEstimate:
    """The followed person: ``xy`` and ``velocity`` in the map frame, ``covariance`` (4 x 4, of x, y, vx,
    vy), ``track_id`` (a new one every acquisition), ``t_s`` of the estimate, ``last_seen_s`` (the last
    measurement, a camera bearing included), ``scan_seen_s`` (the last scan that showed the person; None:
    not kept apart)."""

    xy: tuple[float, float]
    velocity: tuple[float, float]
    covariance: FloatArray
    track_id: int
    t_s: float
    last_seen_s: float
    scan_seen_s: float | None = None

    @property
    def speed_mps(self) -> float:
        return math.hypot(*self.velocity)


class PersonTracker:
    """One person's track; see the module's text."""

    def __init__(self, config: TrackerConfig = TrackerConfig()) -> None:
        self.config = config
        self.x: FloatArray | None = None
        self.p: FloatArray | None = None
        self.t_s = -math.inf
        self.last_seen_s = -math.inf
        self.scan_seen_s = -math.inf  # the last scan measurement (bearings not counted)
        self.track_id = 0
        self.counts: dict[str, int] = {"acquired": 0, "lost": 0, "updates": 0, "rejected": 0}
        self.last_lost: PersonEstimate | None = None  # the track when it was dropped

    @property
    def tracking(self) -> bool:
        return self.x is not None

    def predict(self, t_s: float, looked_s: float | None = None) -> None:
        """Move the track to ``t_s``; drop it when no measurement was accepted for ``lost_after_s`` up to
        ``looked_s``, the last time the sensors looked for the person (None: ``t_s``): a scan that is late
        does not drop the track, a scan that does not show the person does."""
        if self.x is None or self.p is None:
            return
        looked = t_s if looked_s is None else min(t_s, looked_s)
        # The scans' measurements only: camera bearings refine a track, they do not keep it alive (chained,
        # each refreshing the last measurement, they held a track the scans no longer gated for 10 s).
        if looked - self.scan_seen_s > self.config.lost_after_s:
            self.drop()
            return
        dt = t_s - self.t_s
        if dt <= 0.0:
            return
        f = np.eye(4)
        f[0, 2] = f[1, 3] = dt
        q1 = self.config.accel_sd_mps2**2 * np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
        q = np.zeros((4, 4))
        q[np.ix_([0, 2], [0, 2])] = q1
        q[np.ix_([1, 3], [1, 3])] = q1
        self.x = f @ self.x
        self.p = f @ self.p @ f.T + q
        self.t_s = t_s

    def acquire(
        self, t_s: float, detections: PersonDetections, robot: Pose, centre_rad: float, half_width_rad: float
    ) -> bool:
        """Start a track on a candidate whose bearing (robot frame) is within ``centre_rad`` +-
        ``half_width_rad`` and range within ``max_acquire_range_m``: within ``reacquire_s`` of a loss only one
        near where the lost person would be by now (the nearest to it), later the one nearest the robot.
        False if none."""
        if len(detections) == 0:
            return False
        d = detections.centres - np.array(robot[:2])
        rng = np.hypot(d[:, 0], d[:, 1])
        bearing = np.arctan2(d[:, 1], d[:, 0]) - robot[2]
        off = np.abs(np.remainder(bearing - centre_rad + np.pi, 2 * np.pi) - np.pi)
        ok = (off <= half_width_rad) & (rng <= self.config.max_acquire_range_m)
        lost = self.last_lost
        if lost is not None and t_s - lost.last_seen_s <= self.config.reacquire_s:
            # Where the lost person would be by now (walking on at their speed, at most 1.5 s of it).
            ahead = min(t_s - lost.last_seen_s, 1.5)
            guess = np.array(lost.xy) + ahead * np.array(lost.velocity)
            near = np.hypot(*(detections.centres - guess).T)
            reach = self.config.reacquire_m + 0.5 * (t_s - lost.last_seen_s)
            close = ok & (near <= reach)
            if not np.any(close):
                return False  # nobody where they would be: rather no track than someone else's
            return self._start(t_s, detections, int(np.flatnonzero(close)[np.argmin(near[close])]))
        if not np.any(ok):
            return False
        return self._start(t_s, detections, int(np.flatnonzero(ok)[np.argmin(rng[ok])]))

    def _start(self, t_s: float, detections: PersonDetections, k: int) -> bool:
        cfg = self.config
        self.x = np.array([*detections.centres[k], 0.0, 0.0])
        self.p = np.diag([cfg.position_sd_m**2] * 2 + [cfg.initial_speed_sd_mps**2] * 2)
        self.t_s = self.last_seen_s = self.scan_seen_s = t_s
        self.track_id += 1
        self.counts["acquired"] += 1
        return True

    def update_detections(
        self, t_s: float, detections: PersonDetections, looked_s: float | None = None
    ) -> bool:
        """The gated nearest candidate (Mahalanobis) as a position measurement; False when none passes.
        ``looked_s``: the previous look (scan) before this one, for :meth:`predict`'s drop."""
        self.predict(t_s, looked_s)
        if self.x is None or self.p is None or len(detections) == 0:
            return False
        h = np.zeros((2, 4))
        h[0, 0] = h[1, 1] = 1.0
        s = h @ self.p @ h.T + np.eye(2) * self.config.position_sd_m**2
        s_inv = np.linalg.inv(s)
        innov = detections.centres - self.x[:2]
        d2 = np.einsum("ni,ij,nj->n", innov, s_inv, innov)
        k = int(np.argmin(d2))
        if d2[k] > GATE_CHI2_2DOF:
            self.counts["rejected"] += 1
            return False
        gain = self.p @ h.T @ s_inv
        self.x = self.x + gain @ innov[k]
        self.p = (np.eye(4) - gain @ h) @ self.p
        self.last_seen_s = max(self.last_seen_s, t_s)
        self.scan_seen_s = max(self.scan_seen_s, t_s)
        self.counts["updates"] += 1
        return True

    def update_bearing(
        self, t_s: float, robot_xy: tuple[float, float], bearing_rad: float, sd_rad: float
    ) -> bool:
        """A bearing (map frame) from ``robot_xy`` to the person, e.g. the forward camera tracker's, as an
        extended Kalman update; gated at 3 sigma. False when rejected or not tracking. A bearing never
        drops the track (only the scans, which look for the person, do: :meth:`predict`'s ``looked_s``)."""
        self.predict(t_s, self.last_seen_s)
        if self.x is None or self.p is None:
            return False
        dx, dy = self.x[0] - robot_xy[0], self.x[1] - robot_xy[1]
        r2 = dx * dx + dy * dy
        if r2 < 1e-6:
            return False
        h = np.array([[-dy / r2, dx / r2, 0.0, 0.0]])
        innov = math.remainder(bearing_rad - math.atan2(dy, dx), math.tau)
        s = float((h @ self.p @ h.T)[0, 0]) + sd_rad**2
        if innov * innov / s > GATE_CHI2_1DOF:
            self.counts["rejected"] += 1
            return False
        gain = (self.p @ h.T / s)[:, 0]
        self.x = self.x + gain * innov
        self.p = (np.eye(4) - np.outer(gain, h[0])) @ self.p
        self.last_seen_s = max(self.last_seen_s, t_s)  # an old measurement does not age the track
        self.counts["updates"] += 1
        return True

    def reframe(self, old_robot: Pose, new_robot: Pose) -> None:
        """The map frame was corrected under the robot (the fusion relocalized: the robot's pose jumped
        from ``old_robot`` to ``new_robot`` while it did not move): carry the track with it, keeping where
        the person is relative to the robot (position, velocity and covariance turned by the jump)."""
        if self.x is None or self.p is None:
            return
        turn = math.remainder(new_robot[2] - old_robot[2], math.tau)
        c, s = math.cos(turn), math.sin(turn)
        r = np.array([[c, -s], [s, c]])
        j = np.zeros((4, 4))
        j[:2, :2] = j[2:, 2:] = r
        rel = self.x[:2] - np.array(old_robot[:2])
        self.x = np.concatenate([r @ rel + np.array(new_robot[:2]), r @ self.x[2:]])
        self.p = j @ self.p @ j.T

    def estimate(self) -> PersonEstimate | None:
        if self.x is None or self.p is None:
            return None
        return PersonEstimate(
            (float(self.x[0]), float(self.x[1])),
            (float(self.x[2]), float(self.x[3])),
            self.p.copy(),
            self.track_id,
            self.t_s,
            self.last_seen_s,
            self.scan_seen_s,
        )

    def drop(self) -> None:
        if self.x is not None:
            self.counts["lost"] += 1
            self.last_lost = self.estimate()
        self.x = self.p = None
