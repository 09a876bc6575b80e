"""The simulator's scoring holds its memory flat over a long run, and its figures stay exact (counts,
means, maxima, shares, distance) or within the histogram's 0.5 % (percentiles)."""

from __future__ import annotations

import gc
import math
import tracemalloc
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agent.commands.sim import Scorer
from agent.runstats import StreamStats
from agent.runtime import Written
from firmware_protocol.pose_frame import PoseFlags, PoseFrame


@dataclass(frozen=True)
class Pose:
    x_m: float
    y_m: float
    yaw_rad: float


WALL_X_M = 2.05


class Circle:
    """The truth: a circle of 2 m radius at 0.2 m/s."""

    def pose_at(self, t: float) -> Pose:
        a = 0.1 * t
        return Pose(2 * math.cos(a), 2 * math.sin(a), a + math.pi / 2)

    def clearances_m(self, x_m: float, y_m: float, t: float | None = None) -> tuple[float, float]:
        """A wall at x = 2.05 m, which the robot (0.105 m in radius) touches round the circle's east end,
        and no people."""
        return WALL_X_M - x_m - 0.105, math.inf


def frames(n: int, start: int = 0) -> list[tuple[Written, float, float]]:
    """Frames 1/30 s apart, each off the truth by a known error (cm) and yaw error (deg)."""
    rng = np.random.default_rng(start)
    out = []
    truth = Circle()
    for i in range(start, start + n):
        t_us = int(i * 1e6 / 30)
        p = truth.pose_at(t_us * 1e-6)
        err, bearing, yaw_err = rng.gamma(2.0, 0.005), rng.uniform(0, math.tau), rng.normal(0.0, 0.01)
        flags = PoseFlags.ODOMETRY | (PoseFlags.VLP if i % 3 else PoseFlags.SLAM)
        f = PoseFrame(
            i, t_us, p.x_m + err * math.cos(bearing), p.y_m + err * math.sin(bearing), p.yaw_rad + yaw_err
        )
        f = PoseFrame(f.sequence, f.t_us, f.x_m, f.y_m, f.yaw_rad, flags=flags)
        out.append((Written(f, 0, None, 34), math.hypot(f.x_m - p.x_m, f.y_m - p.y_m), abs(yaw_err)))
    return out


def feed(scorer: Scorer, batch: list[tuple[Written, float, float]]) -> None:
    for written, _, _ in batch:
        scorer.observe(written)
    scorer.drain()


def test_the_scorer_keeps_no_more_after_an_hour_of_frames_than_after_a_few_minutes() -> None:
    scorer = Scorer(Circle())  # type: ignore[arg-type]
    minute = frames(1800)
    for _ in range(3):  # the first minutes: the paths fill up and start thinning, the histograms exist
        feed(scorer, minute)
    gc.collect()
    tracemalloc.start()
    try:
        for _ in range(57):  # the rest of an hour at 30 frames/s (the same frames again)
            feed(scorer, minute)
        gc.collect()
        grown, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # Per-frame lists held ~0.5 kB a frame: 102,600 more frames would be ~50 MB. Bounded: the decimated
    # paths swing between 2,000 and 4,000 points each (~0.5 MB for both), nothing else grows.
    assert grown < 1_000_000, grown


def test_the_scores_are_the_exact_figures_and_percentiles_within_half_a_percent(tmp_path: Path) -> None:
    truth_csv = tmp_path / "truth.csv"
    scorer = Scorer(Circle(), truth_csv, path_points=100)  # type: ignore[arg-type]
    batch = frames(5000)
    feed(scorer, batch)
    figures = scorer.figures()
    errors_cm = np.array([100 * e for _, e, _ in batch])
    yaw_deg = np.degrees([y for _, _, y in batch])
    assert figures["pose_error_cm_mean"] == round(float(np.mean(errors_cm)), 3)
    assert figures["pose_error_cm_max"] == round(float(np.max(errors_cm)), 3)
    assert figures["within_2cm"] == round(float(np.mean(errors_cm <= 2.0)), 4)
    p95 = float(np.percentile(errors_cm, 95, method="inverted_cdf"))
    assert abs(figures["pose_error_cm_p95"] - p95) <= 0.005 * p95 + 1e-3  # type: ignore[operator]
    y95 = float(np.percentile(yaw_deg, 95, method="inverted_cdf"))
    assert abs(figures["yaw_error_deg_p95"] - y95) <= 0.005 * y95 + 1e-3  # type: ignore[operator]
    assert figures["source_share"] == {
        "vlp": round(3333 / 5000, 4),
        "slam": round(1667 / 5000, 4),
        "odometry": 1.0,
        "imu": 0.0,
    }
    truth = Circle()
    path = np.array([(p.x_m, p.y_m) for p in (truth.pose_at(w.frame.t_us * 1e-6) for w, _, _ in batch)])
    # Contact: counted once each time the footprint reaches the wall (5000 frames: three passes of the east
    # end, at 0, 62.8 and 125.7 s), the closest approach the deepest frame's.
    gaps = WALL_X_M - path[:, 0] - 0.105
    touching = gaps <= 0
    assert (
        figures["collisions"]
        == figures["collisions_walls"]
        == int(touching[0] + np.sum(touching[1:] & ~touching[:-1]))
    )
    assert figures["collisions"] == 3 and figures["collisions_people"] == 0
    assert figures["clearance_wall_m_min"] == round(float(gaps.min()), 4)
    assert figures["clearance_person_m_min"] is None
    assert figures["distance_m"] == round(float(np.sum(np.hypot(*np.diff(path, axis=0).T))), 3)
    # The picture's paths: bounded, evenly thinned, ending where the path ends.
    points = scorer.truth_path.points()
    assert len(points) <= 101 and points[0] == tuple(path[0]) and points[-1] == tuple(path[-1])
    # The truth per frame is in the file, every frame, once finished.
    assert not truth_csv.exists()
    assert scorer.finish_truth() == truth_csv
    rows = truth_csv.read_text().splitlines()
    assert rows[0] == "sequence,t_us,x_m,y_m,yaw_rad,written_us" and len(rows) == 5001
    seq, _, x, y, _, _ = rows[-1].split(",")
    assert (int(seq), float(x), float(y)) == (4999, path[-1][0], path[-1][1])


def test_stream_stats_percentiles_against_numpy() -> None:
    rng = np.random.default_rng(3)
    values = rng.lognormal(0.0, 2.0, 20_000)
    stats = StreamStats()
    for v in values:
        stats.add(float(v))
    assert stats.count == values.size and stats.max == values.max() and stats.min == values.min()
    assert math.isclose(stats.mean, float(values.mean()), rel_tol=1e-12)
    for q in (1, 50, 95, 99, 99.9, 100):
        exact = float(np.percentile(values, q, method="inverted_cdf"))
        assert abs(stats.percentiles(q)[0] - exact) <= 0.005 * exact, q
    assert math.isnan(StreamStats().percentiles(50)[0])  # nothing added
