"""Feed a recorded log through the SLAM filter as fast as it goes, timing every scan.

This is the loop behind ``vlp-agent eval slam`` and ``benchmarks/slam_update.py``: no printing, no files;
progress is reported through an optional callback.
"""

from __future__ import annotations

import itertools
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from agent.slam.fix import TimedFix
from agent.slam.logs import SlamLog
from agent.slam.pose import between, compose, wrap_angle
from agent.slam.rbpf import RbpfConfig, RbpfSlam, StepKind

FloatArray = npt.NDArray[np.float64]

Progress = Callable[[int, int, "RbpfSlam"], None]


@dataclass(frozen=True)
class ReplayResult:
    """``poses`` (N, 3): the pose of every record of the log along the final best particle's ancestry
    (its pose at each filter update, placed between updates by the odometry carried from the updates
    on either side, :func:`poses_per_record`): the trajectory the final map was built from;
    ``online_poses`` (N, 3): the pose the filter reported right after each record (what a robot would
    have used then); ``mean_poses`` (N, 3): as ``poses``, but along the weighted mean of
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
    slam.finish()  # the final optimisation: the log is over (LoopClosureConfig.final_scan_chain)
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
    odometry: FloatArray,
    slam: RbpfSlam,
    update_records: list[int],
    mean: bool = False,
    blend: bool = True,
) -> FloatArray:
    """One pose per record, given each record's odometry (N, 3) as the filter took it, along the final best
    particle's path at the filter's updates (with ``mean``, the weighted mean over the final particles'
    ancestries, ``RbpfSlam.mean_trajectory``), placed between the updates by :func:`poses_per_record`
    with the filter's own exchange rate of turning for driving (its update gates, 0.25 m per 0.2 rad by
    default)."""
    _, update_poses, update_odom = slam.mean_trajectory() if mean else slam.trajectory()
    # With a bounded history only the last updates are kept: line them up with the newest records.
    kept = update_records[len(update_records) - update_poses.shape[0] :]
    metres_per_rad = slam.config.linear_update_m / slam.config.angular_update_rad
    return poses_per_record(odometry, kept, update_poses, update_odom, metres_per_rad, blend)


def poses_per_record(
    odometry: FloatArray,
    update_records: Sequence[int],
    update_poses: FloatArray,
    update_odom: FloatArray,
    metres_per_rad: float,
    blend: bool = True,
) -> FloatArray:
    """(N, 3) a pose for each record, given each record's odometry (N, 3) and the path at the updates
    (``update_poses`` (U, 3) at the records ``update_records``, increasing, where the odometry read
    ``update_odom`` (U, 3)). An update's record takes its pose. A record between updates k and k+1 is the
    odometry carried forward from update k, x_k ⊕ (o_k⁻¹ ⊕ o_i), and back from update k+1, blended by the
    share of the odometry's motion from k to k+1 already driven at the record (:func:`motion_shares`,
    :func:`blend_between`): the filter corrects the odometry at k+1, and a record just before it should
    carry nearly all of that correction, not none (exp1's URG rover turns 0.2 rad between updates with its
    odometry's turn several degrees off). Records after the last update are carried forward alone (nothing
    later is known), as every record is with ``blend`` False; records before the first update keep the
    odometry itself."""
    poses = np.array(odometry, dtype=np.float64, copy=True)
    bounds = [*update_records, odometry.shape[0]]
    for k, (first, stop) in enumerate(itertools.pairwise(bounds)):
        span = odometry[first:stop]
        forward = compose(update_poses[k], between(update_odom[k], span))
        if not blend or k + 1 >= len(update_records):
            poses[first:stop] = forward
            continue
        backward = compose(update_poses[k + 1], between(update_odom[k + 1], span))
        shares = motion_shares(np.vstack([span, update_odom[k + 1][None, :]]), metres_per_rad)[:-1]
        poses[first:stop] = blend_between(forward, backward, shares)
    return poses


def motion_shares(odometry: FloatArray, metres_per_rad: float) -> FloatArray:
    """(N,) how far along the odometry's motion from its first pose to its last each pose lies, 0 to 1:
    the motion summed record by record (a record's translation plus ``metres_per_rad`` times its turn,
    so that turning on the spot counts). A path without motion gives 0 throughout."""
    steps = between(odometry[:-1], odometry[1:]) if odometry.shape[0] > 1 else np.zeros((0, 3))
    moved = np.hypot(steps[:, 0], steps[:, 1]) + metres_per_rad * np.abs(steps[:, 2])
    travelled = np.concatenate([[0.0], np.cumsum(moved)])
    total = travelled[-1]
    if total <= 0.0:
        return np.zeros(odometry.shape[0])
    shares: FloatArray = travelled / total
    return shares


def blend_between(forward: FloatArray, backward: FloatArray, shares: FloatArray) -> FloatArray:
    """(N, 3) poses ``forward`` (1 - s) + ``backward`` s, the headings on the circle (their difference
    wrapped, then the share of it added)."""
    s = shares[:, None]
    out = forward * (1.0 - s) + backward * s
    out[:, 2] = wrap_angle(forward[:, 2] + shares * wrap_angle(backward[:, 2] - forward[:, 2]))
    return out
