"""Feed a recorded log through the SLAM filter as fast as it goes, timing every scan.

This is the loop behind ``vlp-agent eval slam`` and ``benchmarks/slam_update.py``: no printing, no files;
progress is reported through an optional callback.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from agent.slam.fix import TimedFix
from agent.slam.logs import SlamLog
from agent.slam.pose import between, compose
from agent.slam.rbpf import RbpfConfig, RbpfSlam, StepKind

FloatArray = npt.NDArray[np.float64]

Progress = Callable[[int, int, "RbpfSlam"], None]


@dataclass(frozen=True)
class ReplayResult:
    """``poses`` (N, 3): the pose of every record of the log along the final best particle's ancestry
    (its pose at each filter update, carried between updates by odometry): the trajectory the final map
    was built from; ``online_poses`` (N, 3): the pose the filter reported right after each record (what
    a robot would have used then); ``mean_poses`` (N, 3): as ``poses``, but along the weighted mean of
    every final particle's ancestry (``RbpfSlam.mean_trajectory``: the path's posterior mean, not the
    path any one map was built from); ``update_ms``: the time of each filter update (the scans that were
    not gated away), ``scan_ms`` of every scan."""

    poses: FloatArray
    online_poses: FloatArray
    mean_poses: FloatArray
    update_ms: FloatArray
    scan_ms: FloatArray
    kinds: tuple[StepKind, ...]
    wall_s: float
    cpu_s: float
    slam: RbpfSlam

    @property
    def rejections(self) -> Counter[str]:
        return Counter({reason.value: count for reason, count in self.slam.gate.counts.items()})


def replay(
    log: SlamLog,
    config: RbpfConfig,
    progress: Progress | None = None,
    progress_every_s: float = 2.0,
    fixes: Sequence[TimedFix] = (),
    prior: tuple[npt.NDArray[np.float32], tuple[float, float]] | None = None,
) -> ReplayResult:
    """Run the whole log; see :class:`ReplayResult`. ``fixes`` (in time order) are handed to the filter
    (``RbpfSlam.add_fix``) as soon as a record's time reaches theirs; their handling is timed with the
    record's. ``prior``: a saved map to continue (log-odds, origin; ``RbpfSlam.seed_map``)."""
    slam = RbpfSlam(log.geometry, config)
    if prior is not None:
        slam.seed_map(*prior)
    n = len(log.records)
    scan_ms = np.zeros(n)
    online = np.zeros((n, 3))
    odometry = log.odometry_poses()  # as the filter took it (dropped pose jumps taken out)
    next_fix = 0
    kinds: list[StepKind] = []
    update_records: list[int] = []
    last_progress = time.perf_counter()
    start_wall = last_progress
    start_cpu = time.process_time()
    for i, record in enumerate(log.records):
        t0 = time.perf_counter()
        while next_fix < len(fixes) and fixes[next_fix].t_s <= record.t_s:
            slam.add_fix(fixes[next_fix].fix, fixes[next_fix].odom_pose)
            next_fix += 1
        result = slam.process(record.t_s, record.ranges_m, record.odom_pose)
        t1 = time.perf_counter()
        scan_ms[i] = (t1 - t0) * 1e3
        online[i] = result.pose
        if result.odometry is not None:
            odometry[i] = result.odometry
        kinds.append(result.kind)
        if result.kind in (StepKind.FIRST, StepKind.UPDATED):
            update_records.append(i)
        if progress is not None and t1 - last_progress >= progress_every_s:
            last_progress = t1
            progress(i + 1, n, slam)
    wall_s = time.perf_counter() - start_wall
    cpu_s = time.process_time() - start_cpu
    if progress is not None:
        progress(n, n, slam)
    update_ms = np.array([scan_ms[i] for i, kind in enumerate(kinds) if kind is StepKind.UPDATED])
    return ReplayResult(
        trajectory_per_record(odometry, slam, update_records),
        online,
        trajectory_per_record(odometry, slam, update_records, mean=True),
        update_ms,
        scan_ms,
        tuple(kinds),
        wall_s,
        cpu_s,
        slam,
    )


def trajectory_per_record(
    odometry: FloatArray, slam: RbpfSlam, update_records: list[int], mean: bool = False
) -> FloatArray:
    """One pose per record, given each record's odometry (N, 3) as the filter took it: the final best
    particle's pose at the last update at or before the record (with ``mean``, the weighted mean over
    the final particles' ancestries there, ``RbpfSlam.mean_trajectory``), moved on by the odometry
    since (x_i = x_k ⊕ (o_k⁻¹ ⊕ o_i)). Records before the first accepted scan get the odometry itself."""
    _, update_poses, update_odom = slam.mean_trajectory() if mean else slam.trajectory()
    poses = odometry.copy()
    if not update_records:
        return poses
    # With a bounded history only the last updates are kept: line them up with the newest records.
    update_records = update_records[len(update_records) - update_poses.shape[0] :]
    k = -1
    for i in range(odometry.shape[0]):
        while k + 1 < len(update_records) and update_records[k + 1] <= i:
            k += 1
        if k >= 0:
            poses[i] = compose(update_poses[k], between(update_odom[k], odometry[i]))
    return poses
