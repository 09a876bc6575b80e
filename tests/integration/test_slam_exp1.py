"""The filter on real URG-04LX data (BreezySLAM exp1.dat, first 37 s): the map is coherent.

exp1 has no ground truth, so coherence is measured two ways that do not trust the filter:

* loop closure: after a 25 m loop the rover passes the start again (record ~350, facing the same way).
  Scan j is registered directly against a map of the first scans (correlative search from raw odometry,
  then Gauss-Newton; it lands on the same pose when seeded from the SLAM estimate instead); the SLAM
  trajectory's relative pose start -> j is compared with that registration, and with raw odometry's;
* thin walls: the fraction of occupied cells that lie in walls at most two cells thick with no ghost copy
  beside them (``agent.slam.metrics.wall_thickness``), against the same scans mapped at the raw odometry
  poses; and whether the scans of the way back past the start land on the walls mapped on the way out.
"""

from __future__ import annotations

import numpy as np
import pytest

from agent.slam.grid import GridGeometry, LogOddsModel, ScanPoints, TileRect, integrate_scans, prepare_scan
from agent.slam.logs import SlamLog, read_log
from agent.slam.matcher import DistanceField, MatcherConfig, SearchConfig, correlative_search, match
from agent.slam.metrics import wall_thickness
from agent.slam.pose import between, transform_points
from agent.slam.rbpf import RbpfConfig, StepKind, sweep_offsets, voxel_filter
from agent.slam.replay import ReplayResult, replay
from tests.conftest import DATA

RECORDS = 365
MODEL = LogOddsModel()
GEOMETRY = GridGeometry()


@pytest.fixture(scope="module")
def run() -> tuple[SlamLog, ReplayResult]:
    # Module scope: one filter run for all the checks. Same skip as the ``shared_data`` fixture.
    if not DATA.is_dir():
        pytest.skip(f"reference data not found at {DATA} (set VLP_SHARED to the shared folder)")
    log = read_log(DATA / "slam/breezyslam/exp1.dat", "breezyslam").sliced(0, RECORDS)
    return log, replay(log, RbpfConfig(particles=30, seed=0))


def scan(log: SlamLog, i: int) -> ScanPoints:
    """Record i's scan, de-skewed with the odometry since the record before, as the filter does."""
    g, records = log.geometry, log.records
    offsets = None
    if i > 0:
        motion = between(records[i - 1].odom_pose, records[i].odom_pose)
        offsets = sweep_offsets(g, records[i].t_s - records[i - 1].t_s, motion)
    return prepare_scan(records[i].ranges_m, g.angles_rad, g.mount, 0.1, g.no_return_m, 5.5, 0.025, offsets)


def map_along(
    log: SlamLog, poses: np.ndarray, indices: range | list[int], geometry: GridGeometry = GEOMETRY
) -> tuple[np.ndarray, tuple[float, float]]:
    """Stored log-odds of the scans ``indices`` placed at ``poses``."""
    rect = TileRect.covering(geometry, (-9.0, -6.0), (9.0, 9.0))
    windows = np.zeros((1, rect.shape[0] * 32, rect.shape[1] * 32), dtype=np.int8)
    for i in indices:
        integrate_scans(windows, rect.origin_m(geometry), 0.05, poses[i][None, :], scan(log, i), MODEL, 32)
    return windows[0], rect.origin_m(geometry)


def _registered(log: SlamLog, scans: range, geometry: GridGeometry) -> tuple[float, int, np.ndarray]:
    """(inlier fraction, scan, pose) of the scan among ``scans`` that registers best on a map of the first
    six scans (the rover stood still for them) drawn on ``geometry``'s lattice."""
    odometry = log.odometry_poses()
    stored, origin = map_along(log, np.zeros((len(log), 3)), range(6), geometry)
    field = DistanceField.from_obstacles((stored > MODEL.counts(MODEL.occupied))[None], origin, 0.05, 0.6)
    search = SearchConfig(
        xy_range_m=0.8, xy_step_m=0.05, yaw_range_rad=0.35, yaw_step_rad=0.01, truncate_m=0.3
    )
    best: tuple[float, int, np.ndarray] | None = None
    for j in scans:
        points = voxel_filter(scan(log, j).hit_xy, 0.1, 200)
        coarse, _ = correlative_search(field, 0, points, between(odometry[0], odometry[j]), search)
        registered = match(field, np.zeros(1, dtype=np.int64), points, coarse[None, :], MatcherConfig())
        if registered.ok[0] and (best is None or registered.inlier_fraction[0] > best[0]):
            best = (float(registered.inlier_fraction[0]), j, registered.poses[0])
    assert best is not None and best[0] > 0.5
    return best


def loop_closure_errors(log: SlamLog, poses: np.ndarray, lattices: int = 1) -> tuple[float, float, float]:
    """(SLAM error m, SLAM error deg, odometry error m) of the relative pose start -> revisit, against a
    direct registration of the revisit scan on a map of the first scans.

    That registration is itself a grid match, and the grid's lattice moves it: drawn on 16 lattices
    (phases 0, 1/4, 1/2, 3/4 of a cell per axis) its heading spreads by 0.30 deg (one standard deviation;
    1.07 deg from end to end) and its position by 0.9 cm in x. ``lattices`` n > 1 registers the scan the
    unmoved lattice picks on n x n lattices and takes their mean: a reference free of any one lattice
    (docs/slam.md, "Open problems", the first item, *The loop's measure has a lattice too*)."""
    odometry = log.odometry_poses()
    # The place where the rover passes its start again, found on the raw odometry (no filter involved).
    late = np.arange(300, len(log))
    nearest = int(
        late[np.argmin(np.hypot(odometry[late, 0] - odometry[0, 0], odometry[late, 1] - odometry[0, 1]))]
    )
    assert np.hypot(*(odometry[nearest, :2] - odometry[0, :2])) < 1.0
    # Register the scans around there; keep the one that registers best.
    _, j, truth_like = _registered(log, range(nearest - 10, min(nearest + 11, len(log))), GEOMETRY)
    if lattices > 1:
        steps = [k * GEOMETRY.resolution_m / lattices for k in range(lattices)]
        found = np.array(
            [
                _registered(log, range(j, j + 1), GridGeometry(phase_m=(px, py)))[2]
                for px in steps
                for py in steps
            ]
        )
        yaw = float(np.arctan2(np.sin(found[:, 2]).mean(), np.cos(found[:, 2]).mean()))
        truth_like = np.array([found[:, 0].mean(), found[:, 1].mean(), yaw])
    slam_error = between(truth_like, between(poses[0], poses[j]))
    odometry_error = between(truth_like, between(odometry[0], odometry[j]))
    return (
        float(np.hypot(*slam_error[:2])),
        float(abs(np.degrees(slam_error[2]))),
        float(np.hypot(*odometry_error[:2])),
    )


def test_at_the_revisit_slam_beats_odometry(run: tuple[SlamLog, ReplayResult]) -> None:
    log, result = run
    slam_m, _, odometry_m = loop_closure_errors(log, result.poses)
    assert slam_m < 0.25
    assert slam_m < 0.75 * odometry_m


def test_the_loop_closes(run: tuple[SlamLog, ReplayResult]) -> None:
    # 0.040 m / 0.11 deg with seed 0 (0.075 m / 0.27 deg before the final optimisation); over seeds 0-23
    # the loop closes within 0.1 m / 2 deg for 23 of 24 (seed 20 finds no link: 0.119 m; docs/slam.md,
    # "Loop closure", *The final optimisation*; `python benchmarks/slam_loop.py --seeds $(seq 0 23)`):
    # this guards the seed the other checks use, not every seed.
    log, result = run
    slam_m, slam_deg, _ = loop_closure_errors(log, result.poses)
    assert slam_m < 0.1
    assert slam_deg < 2.0


def test_the_final_optimisation_closes_the_loop_with_the_link_the_graph_agreed_with(
    run: tuple[SlamLog, ReplayResult],
) -> None:
    # The revisit's known-area link agreed with the graph (loops.Verdict.NEAR): no optimisation ran while
    # the filter drove, but the final one holds the chain measured scan to scan to it. Seed 0: 0.075 m as
    # the filter left it, 0.040 m after; seeds 0-5 0.039-0.087 m.
    log, result = run
    assert result.slam.stats.loop_verdicts["near"] >= 1 and result.slam._near_loops
    assert result.slam.stats.final_scan_edges > 0.9 * result.slam.stats.updates
    slam_m, slam_deg, _ = loop_closure_errors(log, result.poses)
    assert slam_m < 0.06
    assert slam_deg < 0.5


def test_the_loop_closes_for_most_seeds(run: tuple[SlamLog, ReplayResult]) -> None:
    # Not one lucky seed: seeds 0-5 close for 6 of 6 (before the final optimisation 5 of 6, seed 3 0.128
    # m; seed 4, 1.37 deg, missed by 2.05 deg before the records between updates took the next update's
    # correction, and seeds 0-5 closed 4 of 6; over seeds 0-23 23 of 24, 19 before the final
    # optimisation, 18 before the blend, 12 also without the grid's phase fitted to the walls); with the
    # correlative search at every update, a former default, they closed for 3 of 6. The bound keeps one
    # seed of margin: a change to the draws moves a seed or two.
    log, result = run
    closed = []
    for seed in range(6):
        poses = result.poses if seed == 0 else replay(log, RbpfConfig(particles=30, seed=seed)).poses
        slam_m, slam_deg, _ = loop_closure_errors(log, poses)
        closed.append(slam_m < 0.1 and slam_deg < 2.0)
    assert sum(closed) >= 5, closed


def test_walls_are_thin_lines(run: tuple[SlamLog, ReplayResult]) -> None:
    log, result = run
    window = result.slam.map_window()
    assert window is not None
    slam_walls = wall_thickness(window[0] > MODEL.occupied)
    # The same scans the filter integrated (its updates), mapped at the raw odometry poses.
    updates = [i for i, kind in enumerate(result.kinds) if kind in (StepKind.FIRST, StepKind.UPDATED)]
    stored, _ = map_along(log, log.odometry_poses(), updates)
    odometry_walls = wall_thickness(stored > MODEL.counts(MODEL.occupied))
    assert slam_walls.occupied_cells > 1500  # a real map, not a few cells
    assert slam_walls.thin_fraction > 0.5
    # The odometry's map: 0.484. The filter's over seeds 0-5: 0.516-0.555 (mean 0.532; before lineages
    # shared a distance field, RbpfConfig.shared_field_updates, 0.506-0.564, mean 0.539): a draw of the
    # filter moves it by ~0.02, so the margin is below every seed's (0.032-0.071).
    assert slam_walls.thin_fraction > odometry_walls.thin_fraction + 0.025


def fraction_on_walls(log: SlamLog, poses: np.ndarray) -> float:
    """Of the endpoints of the scans on the way back past the start (records 320 on) that land near
    something the first 18 s mapped (both placed along ``poses``), the fraction within 5 cm of a wall."""
    stored, origin = map_along(log, poses, range(180))
    field = DistanceField.from_obstacles((stored > MODEL.counts(MODEL.occupied))[None], origin, 0.05, 1.0)
    distances = []
    for i in range(320, len(log)):
        world = transform_points(poses[i], scan(log, i).hit_xy)
        d, _, _ = field.sample(np.zeros(1, dtype=np.int64), world[None, :, 0], world[None, :, 1])
        distances.append(d[0][d[0] < 0.5])
    return float(np.mean(np.concatenate(distances) <= 0.05))


def test_the_return_fits_the_first_map(run: tuple[SlamLog, ReplayResult]) -> None:
    log, result = run
    slam, odometry = fraction_on_walls(log, result.poses), fraction_on_walls(log, log.odometry_poses())
    assert slam > 0.4
    assert slam > odometry + 0.1


def test_speed_figures_are_recorded(run: tuple[SlamLog, ReplayResult]) -> None:
    _log, result = run
    assert result.update_ms.size == result.slam.stats.updates > 60
    assert result.scan_ms.size == RECORDS
    assert result.slam.gate.counts.total() == 0  # exp1 has no bad scans
