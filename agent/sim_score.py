"""The simulator's scoring of the pose stream against the simulation's truth, in bounded memory.

``vlp-agent sim`` may run for hours; what it keeps does not grow with the frames:

* counts, means, maxima, the share of frames within 2 cm, each source bit's share and the distance driven
  are exact (running sums);
* the error percentiles come from a fixed histogram (``agent.runstats.StreamStats``: logarithmic bins,
  within 0.5 % of the exact nearest-rank percentile);
* the true and fused paths for the trajectory picture are decimated: every ``stride``-th point, the stride
  doubling (and every other kept point dropped) each time ``path_points`` are held;
* the truth per frame (``--truth``: the true pose at the frame's ``t_us``, and ``written_us``, when the
  agent finished writing the frame, on the same clock) goes to the file as frames are scored, into a
  temporary file that :meth:`Scorer.finish_truth` renames into place (a reader never sees half a file).
"""

from __future__ import annotations

import collections
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import IO, Protocol

from agent.runstats import StreamStats
from agent.runtime import Written
from firmware_protocol.pose_frame import PoseFlags

__all__ = ["DecimatedPath", "Scorer"]

SOURCES = (PoseFlags.VLP, PoseFlags.SLAM, PoseFlags.ODOMETRY, PoseFlags.IMU)


class _Pose(Protocol):
    @property
    def x_m(self) -> float: ...

    @property
    def y_m(self) -> float: ...

    @property
    def yaw_rad(self) -> float: ...


class TruthSource(Protocol):
    def pose_at(self, t: float) -> _Pose: ...

    def clearances_m(self, x_m: float, y_m: float, t: float | None = None) -> tuple[float, float]: ...


class DecimatedPath:
    """A polyline of at most ``capacity`` points (plus the newest), evenly thinned as it grows."""

    def __init__(self, capacity: int = 4000) -> None:
        if capacity < 2:
            raise ValueError(f"capacity must be >= 2, got {capacity}")
        self.capacity = capacity
        self.stride = 1
        self._seen = 0
        self._kept: list[tuple[float, float]] = []
        self._newest: tuple[float, float] | None = None

    def add(self, x: float, y: float) -> None:
        if self._seen % self.stride == 0:
            self._kept.append((x, y))
            if len(self._kept) >= self.capacity:
                self._kept = self._kept[::2]
                self.stride *= 2
        self._seen += 1
        self._newest = (x, y)

    def points(self) -> list[tuple[float, float]]:
        """The kept points and, if it was not kept, the newest one (so the line ends where the path does)."""
        if self._newest is not None and (not self._kept or self._kept[-1] != self._newest):
            return [*self._kept, self._newest]
        return list(self._kept)

    def __len__(self) -> int:
        return self._seen


class Scorer:
    """Every frame written, compared with the simulation's truth at the frame's time (off the hot path:
    the writer only appends; :meth:`drain` runs in the main loop, well within the truth's 2 s history)."""

    def __init__(self, sim: TruthSource, truth_csv: Path | None = None, path_points: int = 4000) -> None:
        self.sim = sim
        self._backlog: collections.deque[Written] = collections.deque()
        self.errors_cm = StreamStats(low=1e-3, high=1e4)
        self.yaw_errors_deg = StreamStats(low=1e-4, high=360.0)
        self.within_2cm = 0
        self.source_frames = dict.fromkeys(SOURCES, 0)
        self.distance_m = 0.0
        self.fused_path = DecimatedPath(path_points)
        self.truth_path = DecimatedPath(path_points)
        self.last_error_m = math.nan
        # Contact of the robot's footprint with walls and people, on the truth at each frame's time.
        self.clearance_wall_m = math.inf
        self.clearance_person_m = math.inf
        self.collisions = {"walls": 0, "people": 0}  # times contact began
        self._touching = {"walls": False, "people": False}
        self._last_truth: tuple[float, float] | None = None
        self.truth_csv = truth_csv
        # Called with (t_ns, x_m, y_m, yaw_rad) for each truth sampled (vlp-agent sim --record records it).
        self.on_truth: Callable[[int, float, float, float], None] | None = None
        self._truth_tmp: Path | None = None
        self._truth_file: IO[str] | None = None
        if truth_csv is not None:
            truth_csv.parent.mkdir(parents=True, exist_ok=True)
            self._truth_tmp = truth_csv.with_name(f".{truth_csv.name}.{os.getpid()}.tmp")
            self._truth_file = open(self._truth_tmp, "w", encoding="ascii")  # noqa: SIM115 (closed in finish)
            self._truth_file.write("sequence,t_us,x_m,y_m,yaw_rad,written_us\n")

    @property
    def frames(self) -> int:
        return self.errors_cm.count

    def observe(self, written: Written) -> None:
        self._backlog.append(written)

    def drain(self) -> None:
        while self._backlog:
            w = self._backlog.popleft()
            f = w.frame
            truth = self.sim.pose_at(f.t_us * 1e-6)
            err = math.hypot(f.x_m - truth.x_m, f.y_m - truth.y_m)
            self.errors_cm.add(100 * err)
            self.within_2cm += 100 * err <= 2.0
            self.yaw_errors_deg.add(math.degrees(abs(math.remainder(f.yaw_rad - truth.yaw_rad, math.tau))))
            for source in SOURCES:
                if f.flags & source:
                    self.source_frames[source] += 1
            if self._last_truth is not None:
                x0, y0 = self._last_truth
                self.distance_m += math.hypot(truth.x_m - x0, truth.y_m - y0)
            self._last_truth = (truth.x_m, truth.y_m)
            self.fused_path.add(f.x_m, f.y_m)
            self.truth_path.add(truth.x_m, truth.y_m)
            self._contact(truth.x_m, truth.y_m, f.t_us * 1e-6)
            if self._truth_file is not None:
                pose = f"{truth.x_m!r},{truth.y_m!r},{truth.yaw_rad!r}"
                self._truth_file.write(f"{f.sequence},{f.t_us},{pose},{w.done_ns // 1000}\n")
            self.last_error_m = err
            if self.on_truth is not None:
                self.on_truth(f.t_us * 1000, truth.x_m, truth.y_m, truth.yaw_rad)

    def _contact(self, x_m: float, y_m: float, t: float) -> None:
        wall, person = self.sim.clearances_m(x_m, y_m, t)
        self.clearance_wall_m = min(self.clearance_wall_m, wall)
        self.clearance_person_m = min(self.clearance_person_m, person)
        for what, gap in (("walls", wall), ("people", person)):
            touching = gap <= 0.0
            if touching and not self._touching[what]:
                self.collisions[what] += 1
            self._touching[what] = touching

    def finish_truth(self) -> Path | None:
        """Close the truth file and move it into place; its path (None without ``truth_csv``)."""
        if self._truth_file is None or self._truth_tmp is None or self.truth_csv is None:
            return None
        self._truth_file.close()
        self._truth_file = None
        self._truth_tmp.replace(self.truth_csv)
        return self.truth_csv

    def discard(self) -> None:
        """Drop an unfinished truth file (the run failed)."""
        if self._truth_file is not None and self._truth_tmp is not None:
            self._truth_file.close()
            self._truth_file = None
            self._truth_tmp.unlink(missing_ok=True)

    def figures(self) -> dict[str, object]:
        """The summary's scoring figures (``vlp-agent sim --json``)."""
        e, y, n = self.errors_cm, self.yaw_errors_deg, self.frames
        p95 = e.percentiles(95)[0]
        yaw95 = y.percentiles(95)[0]
        return {
            "distance_m": round(self.distance_m, 3),
            "pose_error_cm_mean": round(e.mean, 3) if n else None,
            "pose_error_cm_p95": round(p95, 3) if n else None,
            "pose_error_cm_max": round(e.max, 3) if n else None,
            "within_2cm": round(self.within_2cm / n, 4) if n else None,
            "yaw_error_deg_p95": round(yaw95, 3) if n else None,
            "collisions": self.collisions["walls"] + self.collisions["people"],
            "collisions_walls": self.collisions["walls"],
            "collisions_people": self.collisions["people"],
            "clearance_wall_m_min": round(self.clearance_wall_m, 4)
            if math.isfinite(self.clearance_wall_m)
            else None,
            "clearance_person_m_min": (
                round(self.clearance_person_m, 4) if math.isfinite(self.clearance_person_m) else None
            ),
            "source_share": {
                (s.name or "").lower(): round(self.source_frames[s] / n, 4) if n else 0.0 for s in SOURCES
            },
        }
