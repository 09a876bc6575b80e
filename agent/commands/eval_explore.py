"""``vlp-agent eval explore``: explore a simulated world from an empty map, faster than real time, and report
how much of it was seen, how, and whether the explorer stopped for the right reason.

The robot, its laser, wheels and VLP fixes are those of ``eval nav`` (``agent.slam.simlog``'s fake clock in
10 ms ticks, each beam cast at its own time with the world's range noise, odometry through the wheels'
errors, VLP fixes at 10 Hz); the navigator is ``agent.navigation``'s, driven as ``eval nav`` drives it
(scans at 10 Hz, a control step at 20 Hz). The explorer (``agent.exploration``, picked by ``--explorer``)
gets the map and the pose every control step and hands targets to the navigator; what became of each
target goes back to it.

The map (``--map``):

* ``truth-pose`` (default): the scans integrated into a log-odds grid at the laser's *true* pose; the
  navigator and the explorer are localized by odometry corrected by the VLP fixes (``eval nav``'s), never
  the truth. A map without SLAM's errors (``ate_m`` 0 by construction; ``localization_rmse_m`` is the
  pose the robot drove with): the figures are about exploring;
* ``slam``: ``agent.slam``'s RBPF builds the map from the scans, odometry and VLP fixes, and its pose is
  the robot's; ``ate_m`` is the error of the SLAM poses the map was built at.

Judged on the truth either way, the map itself: ``map_error_m``, the RMS distance from each occupied cell
of the final map to the nearest true wall (walls and closed doors rasterized at the map's resolution).

Judged on the truth: ``explored_fraction`` is the share of the true map's reachable free area (the free
cells 4-connected to the start inside the walls, the walls rasterized at the map's resolution) that the
map knows (free or occupied: seen); ``collisions`` the world robot's footprint touching a wall or a person.

The sp2atm explorer's topological map (HTM: places, possible nodes, edges, rooms) is drawn on the picture
and written beside it as GeoJSON (``agent.exploration.topology``; ``--topology`` to put it elsewhere).
"""

from __future__ import annotations

import argparse
import enum
import json
import math
import sys
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from agent import figure
from agent.commands.eval_nav import CONTROL_EVERY, FIX_GAIN, draw_segments, rasterize_walls
from agent.exploration import (
    Command,
    Decision,
    ExploreConfig,
    ExplorerKind,
    ExploreState,
    GridMap,
    Sp2atmExplorer,
    make_explorer,
)
from agent.exploration.htm import Htm, NodeKind
from agent.navigation.config import NavConfig
from agent.navigation.costmap import BoolArray, Costmap, FloatArray, GridSpec
from agent.navigation.navigator import Goal, Navigator, NavStatus
from drivers.sim.world import World

Float32Array = npt.NDArray[np.float32]

# Log-odds of a hit and of a beam passing through, and the clamp (a person who walked away is cleared in a
# few scans).
L_HIT, L_MISS, L_CLAMP = 1.0, -0.7, 3.5
MAP_EVERY_S = 0.5  # the map handed to the explorer and the navigator's static layer is refreshed this often
DEFAULT_BUDGET_S = 3600.0
PROGRESS_EVERY_S = 60.0
EVIDENCE_S = 1.0  # the hits the explorer is shown as evidence of a passage shut are at most this old


class MapSource(enum.StrEnum):
    TRUTH_POSE = "truth-pose"
    SLAM = "slam"


def add_parser(subparsers: Any) -> None:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "explore",
        help="explore a simulated world from an empty map; report the share explored, path, decisions, "
        "collisions and why it stopped",
        description=textwrap.dedent(
            """\
            Start the simulated robot of --world with an empty map and explore until the explorer says
            complete (or failed, or the time budget is spent), on a simulated clock, faster than real
            time: the laser builds the map, the explorer picks targets, the navigation stack drives
            there. Reports the share of the reachable free area explored, whether it completed and why
            it stopped, the map ATE (the poses the map was built at: --map slam for a map the robot
            built) and the map's own error against the true walls, the localization error, the path
            length, the decisions and their time, retries and branches pruned for a passage seen
            shut, and collisions; writes the map with the path and the frontiers (and sp2atm's topology map:
            rooms, places, edges) as one PNG, and sp2atm's topological map as GeoJSON beside it
            (docs/exploration.md). Progress on stderr."""
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--world", metavar="FILE", default=None, help="the world (default: the shipped office)")
    p.add_argument(
        "--explorer",
        choices=[k.value for k in ExplorerKind],
        default=ExplorerKind.FRONTIER.value,
        help="the explorer (default: frontier)",
    )
    p.add_argument(
        "--map",
        choices=[m.value for m in MapSource],
        default=MapSource.TRUTH_POSE.value,
        help="truth-pose: scans integrated at the true pose (default); slam: the RBPF's map and pose",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed: sensor noise, people (default: 0)")
    p.add_argument(
        "--budget-s",
        type=float,
        default=DEFAULT_BUDGET_S,
        metavar="S",
        help=f"simulated seconds before giving up (default: {DEFAULT_BUDGET_S:g})",
    )
    p.add_argument(
        "--png", metavar="FILE", default="explore.png", help="the picture to write (default: explore.png)"
    )
    p.add_argument(
        "--topology",
        metavar="FILE",
        default=None,
        help="where the sp2atm explorer's topological map (GeoJSON, docs/exploration.md) is written "
        "(default: beside the picture, <png stem>.topology.geojson); the frontier explorer has none",
    )
    p.add_argument("--json", action="store_true", help="print the results as one JSON object on stdout")


# -- the map from scans --------------------------------------------------------------------------------
class ScanMap:
    """A log-odds grid the scans are integrated into at a given laser pose (free along each beam up to
    half a cell short of its end, the end cell hit; beams without a return are left out: a dropout must
    not clear through a wall)."""

    def __init__(self, spec: GridSpec) -> None:
        self.spec = spec
        self.log_odds: Float32Array = np.zeros(spec.shape, dtype=np.float32)
        self.seen: BoolArray = np.zeros(spec.shape, dtype=bool)
        # Whether each cell's latest observation was a hit (the evidence a passage was shut: a door that
        # closed is hit from then on, while the log-odds still remember it open).
        self.last_hit: BoolArray = np.zeros(spec.shape, dtype=bool)
        self.hit_t: FloatArray = np.full(spec.shape, -np.inf)  # when (``t_s`` of ``integrate``)

    def integrate(
        self,
        laser: tuple[float, float, float],
        angles_rad: FloatArray,
        ranges_m: FloatArray,
        min_range_m: float,
        max_range_m: float,
        t_s: float = 0.0,
    ) -> None:
        res = self.spec.resolution_m
        ranges = np.asarray(ranges_m, dtype=np.float64)
        hit = (ranges >= min_range_m) & (ranges <= max_range_m)
        theta = laser[2] + np.asarray(angles_rad, dtype=np.float64)[hit]
        r = ranges[hit]
        c, s = np.cos(theta), np.sin(theta)
        steps = np.arange(0.0, float(r.max(initial=0.0)), res / 2.0)
        along = steps[None, :] < (r[:, None] - res / 2.0)
        px = (laser[0] + c[:, None] * steps[None, :])[along]
        py = (laser[1] + s[:, None] * steps[None, :])[along]
        flat = self.log_odds.reshape(-1)
        passed, ended = self._flat(px, py), self._flat(laser[0] + c * r, laser[1] + s * r)
        # Fancy-index += adds once per distinct cell: each scan counts once for a cell, however many
        # beams pass through it.
        flat[passed] += np.float32(L_MISS)
        flat[ended] += np.float32(L_HIT - L_MISS)
        seen = self.seen.reshape(-1)
        seen[passed] = True
        seen[ended] = True
        last = self.last_hit.reshape(-1)
        last[passed] = False
        last[ended] = True
        self.hit_t.reshape(-1)[ended] = t_s
        np.clip(self.log_odds, -L_CLAMP, L_CLAMP, out=self.log_odds)

    def recent_hits(self, t_s: float, within_s: float) -> FloatArray:
        """The centres (metres) of the cells whose latest observation was a hit no older than
        ``within_s``: what the laser sees occupied now (a person's trail of older hits left out)."""
        cells = np.argwhere(self.last_hit & (self.hit_t >= t_s - within_s))
        return self.spec.to_world(cells)

    def _flat(self, x: FloatArray, y: FloatArray) -> npt.NDArray[np.intp]:
        rows, cols = self.spec.shape
        col = np.floor((x - self.spec.origin_m[0]) / self.spec.resolution_m).astype(np.intp)
        row = np.floor((y - self.spec.origin_m[1]) / self.spec.resolution_m).astype(np.intp)
        ok = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
        out: npt.NDArray[np.intp] = row[ok] * cols + col[ok]
        return out


def grid_from_log_odds(spec: GridSpec, log_odds: Float32Array, seen: BoolArray | None = None) -> GridMap:
    """Unknown: never observed (``seen``; without it, log-odds 0); occupied: more evidence of a hit than of
    a pass (p > 0.5), so a cell at a wall's surface that noise flips between hit and pass stays a wall
    instead of flickering to unknown and back (each flicker a false frontier); free: the rest."""
    unknown = ~seen if seen is not None else log_odds == 0.0
    occupied = ~unknown & (log_odds > 0.0)
    return GridMap(spec, occupied, unknown)


class SlamMap:
    """``agent.slam``'s RBPF as the map and pose source, its map resampled onto the evaluation's grid."""

    def __init__(self, world: World, spec: GridSpec, seed: int) -> None:
        from agent.slam.rbpf import RbpfConfig, RbpfSlam
        from agent.slam.simlog import laser_geometry

        start = world.robot.start
        self.spec = spec
        self.slam = RbpfSlam(
            laser_geometry(world), RbpfConfig(initial_pose=(start.x_m, start.y_m, start.yaw_rad), seed=seed)
        )
        res = spec.resolution_m
        rows, cols = spec.shape
        self._x = spec.origin_m[0] + (np.arange(cols) + 0.5) * res
        self._y = spec.origin_m[1] + (np.arange(rows) + 0.5) * res

    def log_odds(self) -> Float32Array:
        out: Float32Array = np.zeros(self.spec.shape, dtype=np.float32)
        window = self.slam.map_window()
        if window is None:
            return out
        values, (ox, oy) = window
        res = self.slam.config.grid.resolution_m
        col = np.floor((self._x - ox) / res).astype(np.intp)
        row = np.floor((self._y - oy) / res).astype(np.intp)
        cols_ok = (col >= 0) & (col < values.shape[1])
        rows_ok = (row >= 0) & (row < values.shape[0])
        out[np.ix_(rows_ok, cols_ok)] = values[np.ix_(row[rows_ok], col[cols_ok])]
        return out


# -- the truth -----------------------------------------------------------------------------------------
def reachable_free(spec: GridSpec, occupied: BoolArray, start: tuple[float, float]) -> BoolArray:
    """The true map's free cells 4-connected to the start cell (inside the walls)."""
    free = (~occupied).astype(np.uint8)
    _, labels = cv2.connectedComponents(free, connectivity=4, ltype=cv2.CV_32S)
    cell = spec.to_cell(np.array(start))[0]
    label = int(labels[cell[0], cell[1]])
    out: BoolArray = (labels == label) & ~occupied
    return out


# -- the run ---------------------------------------------------------------------------------------------
@dataclass
class _Run:
    truth: list[tuple[float, float]] = field(default_factory=list)
    estimate: list[tuple[float, float]] = field(default_factory=list)
    errors_m2: list[float] = field(default_factory=list)  # the pose the robot drove with, at every scan
    map_errors_m2: list[float] = field(default_factory=list)  # the pose the map was built at, each scan
    targets: list[tuple[float, float]] = field(default_factory=list)
    decision_ms: list[float] = field(default_factory=list)
    decision_cpu_ms: list[float] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    collisions_walls: int = 0
    collisions_people: int = 0
    touching: bool = False
    path_m: float = 0.0
    last_decision: Decision | None = None
    htm: Htm | None = None  # the sp2atm explorer's topology map at the end


@dataclass
class Exploration:
    """What one run leaves: the summary (JSON-ready), the picture, the topological map (GeoJSON dict;
    None for an explorer that makes none) and the final map."""

    summary: dict[str, Any]
    picture: npt.NDArray[np.uint8]
    topology: dict[str, Any] | None
    grid: GridMap


def run_exploration(
    world: World,
    explorer_kind: ExplorerKind,
    seed: int,
    map_source: MapSource = MapSource.TRUTH_POSE,
    budget_s: float = DEFAULT_BUDGET_S,
    progress: bool = False,
    config: ExploreConfig | None = None,
) -> Exploration:
    """Explore ``world`` (see the module docstring): the summary (JSON-ready), the picture, the topological
    map (GeoJSON dict) for an explorer that makes one (sp2atm, else None) and the final map."""
    from agent.slam.fix import PoseFix
    from agent.slam.pose import between, compose
    from agent.slam.simlog import TICK_S, simulated_sensors
    from drivers.sim.simulation import Simulation

    robot = world.robot
    nav = NavConfig(
        radius_m=robot.radius_m,
        track_m=robot.track_m,
        max_wheel_speed_mps=robot.max_wheel_radps * robot.wheel_radius_m,
    )
    config = config or ExploreConfig(explorer=explorer_kind)
    sensors = simulated_sensors(world, seed)
    clock, sim, geometry = sensors.clock, sensors.sim, sensors.geometry
    scanner, odometry, fixes = sensors.scanner, sensors.odometry, sensors.fixes
    spec, walls_occupied = rasterize_walls(world, nav.resolution_m)
    start = robot.start
    target_area = _true_area(spec, walls_occupied, sim, (start.x_m, start.y_m))
    area_at_start_m2 = float(target_area.sum()) * spec.resolution_m**2
    scan_map = ScanMap(spec) if map_source is MapSource.TRUTH_POSE else None
    slam_map = SlamMap(world, spec, seed) if map_source is MapSource.SLAM else None
    all_unknown = np.ones(spec.shape, dtype=bool)
    mount = robot.laser_mount
    navigator = Navigator(
        nav,
        Costmap(spec, np.zeros(spec.shape, bool), all_unknown, nav),
        (mount.x_m, mount.y_m, mount.yaw_rad),
    )
    explorer = make_explorer(config, nav)
    # The evidence a failed target's way was shut (a door closed): the cells whose latest observation,
    # from the estimated pose, was a hit.
    hits = ScanMap(spec)
    explorer.evidence = lambda: hits.recent_hits(clock.t_s, EVIDENCE_S)
    min_m, max_m = world.laser.min_range_mm / 1000.0, world.laser.max_range_mm / 1000.0
    scan_every = max(round(60.0 / world.laser.scan_rpm / TICK_S), 1)
    fix_every = max(round(1.0 / fixes.rate_hz / TICK_S), 1)
    map_every = max(round(MAP_EVERY_S / TICK_S), 1)

    estimate = np.array([start.x_m, start.y_m, start.yaw_rad])
    last_odometry = odometry.pose.copy()
    pose = (start.x_m, start.y_m, start.yaw_rad)
    explorer.command(Command.START, pose, 0.0)
    grid = GridMap(spec, np.zeros(spec.shape, bool), all_unknown)
    run = _Run()
    reported = True  # the navigator's outcome for the current goal has been passed on
    stopped_reason = ""
    wall_start = time.perf_counter()
    last_progress = 0.0

    def report(t_s: float, state: str) -> None:
        """One progress line on stderr: the share of the true area explored on the current map."""
        seen = float(np.count_nonzero(target_area & ~grid.unknown)) / max(int(target_area.sum()), 1)
        print(
            f"  t={t_s:6.0f} s  explored {seen:6.1%}  path {run.path_m:6.1f} m  decisions "
            f"{len(run.decision_ms)}  {state}",
            file=sys.stderr,
            flush=True,
        )

    tick = 0
    last = (start.x_m, start.y_m)
    scanned = False
    while True:
        tick += 1
        clock.t_s = t = tick * TICK_S
        truth = sim.pose()
        run.path_m += math.hypot(truth.x_m - last[0], truth.y_m - last[1])
        last = (truth.x_m, truth.y_m)
        _contact(run, sim, world, sim.segments(), last)
        odometry.update(sim.wheels().position_rad)
        if tick % fix_every == 0:
            got = fixes(sim, t, odometry.pose)
            fix: PoseFix | None = None if isinstance(got, str) else got[1]
        else:
            fix = None
        if slam_map is None:
            estimate = compose(estimate, between(last_odometry, odometry.pose))
            last_odometry = odometry.pose.copy()
            if fix is not None:
                estimate[0] += FIX_GAIN * (fix.x_m - estimate[0])
                estimate[1] += FIX_GAIN * (fix.y_m - estimate[1])
                if fix.yaw_rad is not None:
                    estimate[2] += FIX_GAIN * math.remainder(fix.yaw_rad - estimate[2], math.tau)
        else:
            if fix is not None:
                slam_map.slam.add_fix(fix, odometry.pose)
            estimate = slam_map.slam.pose(odometry.pose)
        pose = (float(estimate[0]), float(estimate[1]), float(estimate[2]))
        if tick % scan_every == 0:
            ranges = scanner.ranges(t)
            if scan_map is not None:
                laser = Simulation.mount_pose(truth, mount.x_m, mount.y_m, mount.yaw_rad)
                scan_map.integrate(
                    (laser.x_m, laser.y_m, laser.yaw_rad), geometry.angles_rad, ranges, min_m, max_m
                )
            elif slam_map is not None:
                slam_map.slam.process(t, ranges, odometry.pose)
                estimate = slam_map.slam.pose(odometry.pose)
                pose = (float(estimate[0]), float(estimate[1]), float(estimate[2]))
            est_laser = Simulation.mount_pose(
                type(truth)(pose[0], pose[1], pose[2]), mount.x_m, mount.y_m, mount.yaw_rad
            )
            hits.integrate(
                (est_laser.x_m, est_laser.y_m, est_laser.yaw_rad),
                geometry.angles_rad,
                ranges,
                min_m,
                max_m,
                t,
            )
            run.truth.append(last)
            run.estimate.append((pose[0], pose[1]))
            run.errors_m2.append((pose[0] - truth.x_m) ** 2 + (pose[1] - truth.y_m) ** 2)
            run.map_errors_m2.append(0.0 if scan_map is not None else run.errors_m2[-1])
            command = navigator.on_scan(t, pose, geometry.angles_rad, ranges, min_m, max_m)
            sim.set_body_velocity(command.v_mps, command.omega_radps)
            scanned = True
        if tick % map_every == 0 and scanned:
            grid = _grid(spec, scan_map, slam_map)
            navigator.costmap.set_static(grid.occupied, grid.unknown)
        if tick % CONTROL_EVERY != 0 or not scanned:
            continue
        decision = explorer.update(grid, pose, t)
        run.last_decision = decision if decision.decided else run.last_decision
        if decision.decided:
            run.decision_ms.append(decision.decision_ms)
            run.decision_cpu_ms.append(decision.decision_cpu_ms)
        if decision.new_target:
            if decision.target is None:
                navigator.cancel("the explorer has no target")
            else:
                tg = decision.target
                navigator.set_goal(Goal(tg.x_m, tg.y_m, tg.yaw_rad), t)
                run.targets.append((tg.x_m, tg.y_m))
                reported = False
        out = navigator.step(t, pose)
        sim.set_body_velocity(out.command.v_mps, out.command.omega_radps)
        if not reported and out.status is NavStatus.REACHED:
            explorer.report_reached(t)
            reported = True
        elif not reported and out.status is NavStatus.FAILED:
            run.failures.append(out.reason)
            explorer.report_failed(out.reason, t)
            reported = True
        if explorer.state in (ExploreState.COMPLETE, ExploreState.FAILED):
            stopped_reason = f"{explorer.state.value}: {explorer.reason}"
            break
        if t >= budget_s:
            stopped_reason = (
                f"time budget of {budget_s:g} s spent ({explorer.state.value}: {explorer.reason})"
            )
            break
        if progress and t - last_progress >= PROGRESS_EVERY_S:
            last_progress = t
            report(t, f"{explorer.state.value}: {explorer.reason}")
    sim.set_body_velocity(0.0, 0.0)
    wall_s = time.perf_counter() - wall_start
    if progress:
        report(clock.t_s, f"end: {stopped_reason}")
    grid = _grid(spec, scan_map, slam_map)
    # Judged on the building as it is at the end: a door that closed during the run cuts off what lies
    # behind it (the robot, wherever it is, could not get there now).
    if world.doors:
        target_area = _true_area(spec, walls_occupied, sim, last)
    known = target_area & ~grid.unknown
    summary = {
        "world": world.name,
        "explorer": explorer_kind.value,
        "seed": seed,
        "map_source": map_source.value,
        "explored_fraction": round(float(np.count_nonzero(known)) / max(int(target_area.sum()), 1), 4),
        "reachable_free_m2": round(float(target_area.sum()) * spec.resolution_m**2, 2),
        "reachable_free_m2_at_start": round(area_at_start_m2, 2),
        "door_events": [
            {"t_s": round(t_s, 1), "door": name, "closed": closed} for t_s, name, closed in sim.door_events()
        ],
        "complete": explorer.state is ExploreState.COMPLETE,
        "state": explorer.state.value,
        "stopped_reason": stopped_reason,
        "ate_m": _rms(run.map_errors_m2),
        "localization_rmse_m": _rms(run.errors_m2),
        **map_error(grid, sim),
        "path_length_m": round(run.path_m, 2),
        "time_s": round(clock.t_s, 1),
        "decisions": len(run.decision_ms),
        "decision_ms_median": round(float(np.median(run.decision_ms)), 2) if run.decision_ms else None,
        "decision_ms_max": round(float(np.max(run.decision_ms)), 2) if run.decision_ms else None,
        "decision_cpu_ms_median": (
            round(float(np.median(run.decision_cpu_ms)), 2) if run.decision_cpu_ms else None
        ),
        "targets": len(run.targets),
        "retries": getattr(explorer, "retries", 0),
        "target_switches": getattr(explorer, "switches", 0),
        "blocked_branches": list(getattr(explorer, "blocked_branches", [])),
        "navigation_failures": len(run.failures),
        "collisions": run.collisions_walls + run.collisions_people,
        "collisions_walls": run.collisions_walls,
        "collisions_people": run.collisions_people,
        "wall_s": round(wall_s, 1),
        "realtime_factor": round(clock.t_s / wall_s, 1) if wall_s > 0 else None,
        "localization": (
            "wheel odometry corrected by simulated VLP fixes (eval nav's); the map from the true pose"
            if map_source is MapSource.TRUTH_POSE
            else "agent.slam RBPF (30 particles) with VLP fixes: its map and its pose"
        ),
    }
    topology: dict[str, Any] | None = None
    if isinstance(explorer, Sp2atmExplorer):
        run.htm = explorer.htm
        kinds = [n.kind for n in explorer.htm.nodes.values()]
        summary["htm_places"] = kinds.count(NodeKind.PLACE)
        summary["htm_possible"] = kinds.count(NodeKind.POSSIBLE)
        summary["htm_edges"] = len(explorer.htm.edges)
        summary["regions"] = kinds.count(NodeKind.REGION)
        summary["backtracks"] = explorer.backtracks
        topology = explorer.topology(map_name=f"{world.name} (eval explore, seed {seed})")
    picture = explore_picture(grid, run, world.name, summary)
    return Exploration(summary, picture, topology, grid)


def explored_share(grid: GridMap, world: World, sim: Any) -> tuple[float, float]:
    """The share of the true reachable free area (the world's walls and its doors as they are now,
    rasterized at the grid's resolution, 4-connected to the robot's true position) that ``grid`` has
    seen, and that area in m²: ``eval explore``'s ``explored_fraction`` for a map of any extent (the
    agent's SLAM map grows as it goes)."""
    spec, walls = rasterize_walls(world, grid.spec.resolution_m)
    truth = sim.pose()
    area = _true_area(spec, walls, sim, (truth.x_m, truth.y_m))
    cells = np.argwhere(area)
    centres = spec.to_world(cells)
    theirs = grid.spec.to_cell(centres)
    inside = grid.spec.inside(theirs)
    seen = np.zeros(len(cells), dtype=bool)
    seen[inside] = ~grid.unknown[theirs[inside, 0], theirs[inside, 1]]
    total = max(len(cells), 1)
    return float(np.count_nonzero(seen)) / total, float(len(cells)) * spec.resolution_m**2


def _rms(squares: list[float]) -> float | None:
    return round(math.sqrt(float(np.mean(squares))), 4) if squares else None


def map_error(grid: GridMap, sim: Any) -> dict[str, float | None]:
    """The map against the truth: for each occupied cell of ``grid``, how far the nearest true wall
    (the world's segments: walls, outlines, the doors closed now) lies beyond the cell (the distance from
    its centre less half its diagonal, at least 0: a cell the wall passes through is exact), RMS and 95th
    percentile. People's marks left in the map count as errors."""
    segments = np.asarray(sim.segments(), dtype=np.float64).reshape(-1, 4)
    points = grid.spec.to_world(np.argwhere(grid.occupied))
    if not len(points) or not len(segments):
        return {"map_error_m": None, "map_error_p95_m": None}
    a, d = segments[:, :2], segments[:, 2:] - segments[:, :2]
    length2 = np.maximum(np.sum(d * d, axis=1), 1e-12)
    nearest = np.empty(len(points))
    for i in range(0, len(points), 2048):
        p = points[i : i + 2048, None, :]
        t = np.clip(np.sum((p - a) * d, axis=2) / length2, 0.0, 1.0)
        nearest[i : i + 2048] = np.min(np.hypot(*np.moveaxis(a + t[..., None] * d - p, 2, 0)), axis=1)
    beyond = np.maximum(nearest - grid.spec.resolution_m / math.sqrt(2.0), 0.0)
    return {
        "map_error_m": round(float(np.sqrt(np.mean(beyond**2))), 4),
        "map_error_p95_m": round(float(np.percentile(beyond, 95)), 4),
    }


def _true_area(spec: GridSpec, walls: BoolArray, sim: Any, xy: tuple[float, float]) -> BoolArray:
    """The free cells 4-connected to ``xy`` with the walls and the doors closed now."""
    occupied = walls.copy()
    draw_segments(spec, occupied, sim.segments())
    return reachable_free(spec, occupied, xy)


def _grid(spec: GridSpec, scan_map: ScanMap | None, slam_map: SlamMap | None) -> GridMap:
    if scan_map is not None:
        return grid_from_log_odds(spec, scan_map.log_odds, scan_map.seen)
    assert slam_map is not None
    return grid_from_log_odds(spec, slam_map.log_odds())


def _contact(run: _Run, sim: Any, world: World, segments: FloatArray, xy: tuple[float, float]) -> None:
    """Count each new contact of the robot's footprint with a wall or a person, on the truth."""
    from drivers.sim.raycast import distance_to_segments

    radius = world.robot.radius_m
    wall = distance_to_segments(xy, segments) - radius <= 0.0
    person = any(
        math.hypot(p[0] - xy[0], p[1] - xy[1]) - q.radius_m - radius <= 0.0
        for q in world.people
        for p in (sim.person_position(q),)
    )
    touching = wall or person
    if touching and not run.touching:
        if person:
            run.collisions_people += 1
        else:
            run.collisions_walls += 1
    run.touching = touching


# -- the picture -----------------------------------------------------------------------------------------
FRONTIER: figure.Colour = (0, 140, 255)  # orange: frontier cells left at the end
TARGET: figure.Colour = (200, 0, 200)  # magenta: the targets the explorer chose
MIN_MAP_PX = 800
MARGIN_LEFT, MARGIN_TOP, MARGIN_BOTTOM, GAP, PANEL_MIN = 80, 66, 62, 24, 260


HTM_PLACE: figure.Colour = (160, 60, 0)  # dark blue: PLACE nodes
HTM_POSSIBLE: figure.Colour = (0, 100, 230)  # orange-red rings: POSSIBLE nodes
HTM_EDGE: figure.Colour = (210, 150, 60)  # light blue: HTM edges
HTM_REGION: figure.Colour = (150, 40, 150)  # purple: region outlines


def draw_htm(canvas: npt.NDArray[np.uint8], axes: figure.Axes, htm: Htm) -> None:
    """The HTM over the map: region outlines with their ids and names, edges, places, possible nodes."""
    for r in htm.regions():
        pts = np.array([axes.to_px(x, y) for x, y in r.polygon], np.int32).reshape(-1, 1, 2)
        cv2.polylines(canvas, [pts], True, HTM_REGION, 2, cv2.LINE_AA)
        label = f"R{r.id}" + (f" {r.name}" if r.name else "")
        cx, cy = axes.to_px(r.x_m, r.y_m)
        figure.text(canvas, label, (cx - 14, cy), 0.5, HTM_REGION)
    for (a, b), _ in htm.edges.items():
        na, nb = htm.nodes[a], htm.nodes[b]
        cv2.line(canvas, axes.to_px(na.x_m, na.y_m), axes.to_px(nb.x_m, nb.y_m), HTM_EDGE, 1, cv2.LINE_AA)
    for n in htm.nodes.values():
        if n.kind is NodeKind.PLACE:
            cv2.circle(canvas, axes.to_px(n.x_m, n.y_m), 5, HTM_PLACE, -1, cv2.LINE_AA)
        elif n.kind is NodeKind.POSSIBLE:
            cv2.circle(canvas, axes.to_px(n.x_m, n.y_m), 6, HTM_POSSIBLE, 2, cv2.LINE_AA)


def explore_picture(
    grid: GridMap, run: _Run, world_name: str, summary: dict[str, Any]
) -> npt.NDArray[np.uint8]:
    """The final map (free white, unknown grey, occupied black), the true path, the estimated path, every
    target chosen, the frontier cells left at the end, the sp2atm explorer's HTM (regions, edges, places,
    possible nodes); a legend, a scale bar, axes in metres, the figures."""
    from agent.exploration.frontiers import frontier_mask

    spec = grid.spec
    rows, cols = spec.shape
    k = max(1, math.ceil(MIN_MAP_PX / max(rows, cols, 1)))
    map_w, map_h = cols * k, rows * k
    base = np.full((rows, cols, 3), 205, np.uint8)
    base[~grid.unknown & ~grid.occupied] = 254
    base[grid.occupied] = 0
    base[frontier_mask(grid.free, grid.unknown, grid.occupied)] = FRONTIER
    canvas: npt.NDArray[np.uint8] = np.ascontiguousarray(
        cv2.resize(base[::-1], (map_w, map_h), interpolation=cv2.INTER_NEAREST), dtype=np.uint8
    )
    x0, y0 = spec.origin_m
    res = spec.resolution_m
    bounds = (x0, x0 + cols * res, y0, y0 + rows * res)
    local = figure.Axes((0, 0, map_w, map_h), bounds)
    figure.draw_path(canvas, local, np.array(run.truth).reshape(-1, 2), figure.TRUTH, figure.TRUTH_WIDTH_PX)
    figure.draw_path(
        canvas,
        local,
        np.array(run.estimate).reshape(-1, 2),
        figure.FUSED,
        figure.ESTIMATE_WIDTH_PX,
        start=False,
    )
    for i, (tx, ty) in enumerate(run.targets):
        cv2.drawMarker(canvas, local.to_px(tx, ty), TARGET, cv2.MARKER_TILTED_CROSS, 14, 2)
        if i == len(run.targets) - 1:
            cv2.circle(canvas, local.to_px(tx, ty), 10, TARGET, 2, cv2.LINE_AA)
    if run.htm is not None:
        draw_htm(canvas, local, run.htm)
    entries = [
        figure.Entry("true path", figure.TRUTH),
        figure.Entry("estimated path", figure.FUSED),
        figure.Entry("targets chosen (circled: last)", TARGET, figure.Mark.CROSS),
        figure.Entry("frontier cells left", FRONTIER),
        figure.Entry("occupied", (0, 0, 0)),
        figure.Entry("unknown", (205, 205, 205)),
    ]
    if run.htm is not None:
        entries += [
            figure.Entry("HTM place (visited)", HTM_PLACE, figure.Mark.DOT),
            figure.Entry("HTM possible node", HTM_POSSIBLE, figure.Mark.RING),
            figure.Entry("HTM edge", HTM_EDGE),
            figure.Entry("region (room) outline, R<id>", HTM_REGION),
        ]
    legend_w, legend_h = figure.legend_size(entries)
    panel_w = max(legend_w, PANEL_MIN)
    lines = [
        f"explored {summary['explored_fraction']:.1%} of {summary['reachable_free_m2']} m2",
        f"{summary['state']}",
        f"path {summary['path_length_m']} m, {summary['time_s']} s",
        f"{summary['decisions']} decisions, median {summary['decision_cpu_ms_median']} ms CPU",
        f"collisions {summary['collisions']}, map ATE {summary['ate_m']} m, "
        f"map error {summary['map_error_m']} m",
    ]
    width = MARGIN_LEFT + map_w + GAP + panel_w + 16
    height = max(MARGIN_TOP + map_h + MARGIN_BOTTOM, MARGIN_TOP + legend_h + 120 + 22 * len(lines))
    img = np.full((height, width, 3), 255, np.uint8)
    img[MARGIN_TOP : MARGIN_TOP + map_h, MARGIN_LEFT : MARGIN_LEFT + map_w] = canvas
    figure.Axes((MARGIN_LEFT, MARGIN_TOP, MARGIN_LEFT + map_w, MARGIN_TOP + map_h), bounds).draw(img)
    figure.title(
        img,
        f"eval explore: {world_name}, {summary['explorer']} explorer, seed {summary['seed']}, "
        f"map from {summary['map_source']}",
    )
    px = MARGIN_LEFT + map_w + GAP
    figure.legend(img, entries, (px, MARGIN_TOP))
    y = MARGIN_TOP + legend_h + 50
    figure.scale_bar(img, k / res, (px + 10, y))
    figure.text(img, f"1 cell = {res * 100:g} cm; ring: start", (px + 10, y + 34), 0.45)
    for i, line in enumerate(lines):
        figure.text(img, line, (px + 10, y + 60 + 22 * i), 0.45)
    return img


def run(args: argparse.Namespace) -> int:
    from agent.commands.worlds import resolve_world
    from agent.slam.mapio import TOPOLOGY_SUFFIX, save_topology, write_png
    from drivers.errors import ConfigError
    from drivers.sim.worldfile import load_world

    if not args.budget_s > 0.0:
        raise ConfigError("--budget-s", "must be positive")
    path = resolve_world(args.world)
    world = load_world(path)
    print(
        f"vlp-agent eval explore: {path}, {args.explorer} explorer, map from {args.map}, seed {args.seed}",
        file=sys.stderr,
        flush=True,
    )
    e = run_exploration(
        world, ExplorerKind(args.explorer), args.seed, MapSource(args.map), args.budget_s, progress=True
    )
    summary, picture, topology = e.summary, e.picture, e.topology
    png = write_png(Path(args.png), picture)
    summary["png"] = str(png)
    if topology is not None:
        where = Path(args.topology) if args.topology else png.with_name(png.stem + TOPOLOGY_SUFFIX)
        summary["topology"] = str(save_topology(topology, where))
    if args.json:
        print(json.dumps(summary, sort_keys=True))
        return 0
    s = summary
    print(f"vlp-agent eval explore: {path}, {s['explorer']} explorer, seed {s['seed']}")
    print(f"  explored           {s['explored_fraction']:.1%} of {s['reachable_free_m2']} m2 reachable free")
    print(f"  stopped            {s['stopped_reason']}")
    print(f"  path               {s['path_length_m']} m in {s['time_s']} s simulated ({s['wall_s']} s wall)")
    print(
        f"  decisions          {s['decisions']}, median {s['decision_ms_median']} ms "
        f"({s['decision_cpu_ms_median']} ms CPU)"
    )
    print(f"  map ATE            {s['ate_m']} m (the poses the map was built at)")
    print(f"  map error          {s['map_error_m']} m RMS, {s['map_error_p95_m']} m p95 (occupied to walls)")
    print(f"  localization       {s['localization_rmse_m']} m RMS (the pose driven with)")
    print(
        f"  collisions         {s['collisions']} (walls {s['collisions_walls']}, "
        f"people {s['collisions_people']})"
    )
    print(f"  picture            {png}")
    if "topology" in s:
        print(
            f"  topology           {s['topology']} ({s['htm_places']} places, {s['htm_possible']} possible, "
            f"{s['regions']} regions, {s['backtracks']} backtracks)"
        )
    return 0
