"""``vlp-agent eval nav``: drive the simulated robot to random goals with the navigation stack, faster than
real time, and report how well it went.

The robot, its laser, wheels and VLP fixes are those of ``eval slam --world`` (``agent.slam.simlog``: a
fake clock in 10 ms ticks, each beam of a scan cast at its own time with the world's range noise,
wheel odometry through the wheels' errors, VLP fixes at 10 Hz from the true pose plus the LED survey's
error and 5 mm / 0.3 deg noise when two LEDs are in view). The navigator (``agent.navigation``) gets:

* **the map**: the world's walls rasterized at the costmap's resolution, i.e. the map a finished SLAM
  run gives (``map_source`` in the JSON); the people and anything else are only in the scans;
* **the pose**: odometry corrected by each VLP fix with a constant gain (a steady-state Kalman filter
  for 10 Hz fixes of 5 mm over 1 % odometry), never the truth;
* **the scans** (10 Hz) and a control step at 20 Hz.

Goals are random poses, one after another, each from where the last one ended: at least
``GOAL_CLEARANCE_M`` from walls, reachable, not on a person's walking path (a robot parked there would
keep a yielding walker waiting for ever, and be walked into by one who does not yield: people stop for
the robot in their way, as the world file's ``yields`` says, but never step aside), at least
``MIN_GOAL_DISTANCE_M`` away.

Judged on the truth: a goal is reached when the navigator says so and the true pose is within 0.10 m
and 5 deg of it; a collision is the footprint (the world robot's radius) touching a wall or a person
(counted per contact, whoever moved, and whether the robot was moving; each contact with a person is
logged with who closed the gap and what the navigator was doing); the path ratio is the true distance
driven over the shortest collision-free path on the true map (the walls rasterized and grown by the
radius, searched 8-connected then pulled taut by line of sight).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import textwrap
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent.navigation.config import NavConfig
from agent.navigation.costmap import BoolArray, Costmap, FloatArray, GridSpec
from agent.navigation.navigator import Goal, Navigator, NavStatus
from agent.navigation.planner import GlobalPlanner, reachable
from drivers.sim.world import World

GOAL_CLEARANCE_M = 0.30  # a goal's distance from walls at least (beyond the robot's radius)
MIN_GOAL_DISTANCE_M = 1.0
PERSON_PATH_MARGIN_M = 0.30  # goals keep this far beyond the footprints' touching distance
REACHED_M = 0.10
REACHED_DEG = 5.0
FIX_GAIN = 0.3  # share of each VLP fix's residual taken into the pose estimate
CONTROL_EVERY = 5  # ticks (20 Hz)
MAP_MARGIN_M = 0.5


def add_parser(subparsers: Any) -> None:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "nav",
        help="drive the simulated robot to random goals with the navigation stack; report success, "
        "precision, path length against the shortest, collisions, planning time",
        description=textwrap.dedent(
            """\
            Drive the simulated robot of --world to N random reachable goal poses, one after another,
            with the navigation stack (costmap, planner, pure pursuit, collision monitor, recovery) on
            a simulated clock, faster than real time, localized by odometry and VLP fixes. Reports the
            share of goals reached within 0.10 m and 5 deg, collisions with walls and people, the path
            length against the shortest collision-free path on the true map, time, the closest
            approach and the planning time per plan."""
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--world", metavar="FILE", default=None, help="the world (default: the shipped office)")
    p.add_argument("--goals", type=int, default=10, metavar="N", help="goals to drive to (default: 10)")
    p.add_argument("--seed", type=int, default=0, help="random seed: goals, sensor noise (default: 0)")
    p.add_argument("--json", action="store_true", help="print the results as one JSON object on stdout")
    p.add_argument("--progress", action="store_true", help="print each goal's outcome on stderr as it ends")
    p.add_argument(
        "--people-never-yield",
        action="store_true",
        help="people walk through the robot as if it were not there (every person's yields = false), "
        "instead of stopping for it as the world file says",
    )


# -- the true map ------------------------------------------------------------------------------------
def rasterize_walls(world: World, resolution_m: float) -> tuple[GridSpec, BoolArray]:
    """The world's walls as occupied cells of a grid covering them plus ``MAP_MARGIN_M``."""
    segments = np.array([(w.x1_m, w.y1_m, w.x2_m, w.y2_m) for w in world.walls]).reshape(-1, 4)
    if not len(segments):
        raise ValueError(f"world {world.name!r} has no walls to navigate between")
    x0 = float(segments[:, [0, 2]].min()) - MAP_MARGIN_M
    y0 = float(segments[:, [1, 3]].min()) - MAP_MARGIN_M
    x1 = float(segments[:, [0, 2]].max()) + MAP_MARGIN_M
    y1 = float(segments[:, [1, 3]].max()) + MAP_MARGIN_M
    spec = GridSpec(
        (x0, y0), resolution_m, (math.ceil((y1 - y0) / resolution_m), math.ceil((x1 - x0) / resolution_m))
    )
    occupied = np.zeros(spec.shape, dtype=bool)
    draw_segments(spec, occupied, segments)
    return spec, occupied


def draw_segments(spec: GridSpec, occupied: BoolArray, segments: FloatArray) -> None:
    """Mark the cells the (N, 4) segments pass through occupied (sampled every quarter cell)."""
    resolution_m = spec.resolution_m
    for ax, ay, bx, by in np.asarray(segments, dtype=np.float64).reshape(-1, 4):
        n = max(math.ceil(math.hypot(bx - ax, by - ay) / (resolution_m * 0.25)), 1) + 1
        t = np.linspace(0.0, 1.0, n)
        cells = spec.to_cell(np.stack([ax + t * (bx - ax), ay + t * (by - ay)], axis=1))
        cells = cells[spec.inside(cells)]
        occupied[cells[:, 0], cells[:, 1]] = True


class ShortestPaths:
    """Shortest collision-free paths for a circle of the robot's radius on the true map."""

    def __init__(self, spec: GridSpec, occupied: BoolArray, radius_m: float) -> None:
        config = NavConfig(radius_m=radius_m, safety_margin_m=0.0, inflation_radius_m=radius_m)
        self.costmap = Costmap(spec, occupied, np.zeros(spec.shape, dtype=bool), config)
        self.planner = GlobalPlanner(clearance_weight=0.0, coarse_factor=1)

    def length_m(self, start: tuple[float, float], goal: tuple[float, float]) -> float:
        plan = self.planner.plan(self.costmap, start, goal)
        return plan.length_m if plan.ok else math.inf


# -- goals ---------------------------------------------------------------------------------------------
def goal_cells(world: World, costmap: Costmap, start: tuple[float, float]) -> FloatArray:
    """World centres of the cells a goal may be drawn from (see the module docstring)."""
    spec = costmap.spec
    distance = costmap.distance_m()
    ok = distance >= world.robot.radius_m + GOAL_CLEARANCE_M
    rows, cols = np.nonzero(ok)
    xy = spec.to_world(np.stack([rows, cols], axis=1))
    keep = np.ones(len(xy), dtype=bool)
    for person in world.people:
        pts = np.array(person.path, dtype=np.float64).reshape(-1, 2)
        segs = np.hstack([pts, np.roll(pts, -1, axis=0)]) if len(pts) > 1 else np.hstack([pts, pts])
        reach = person.radius_m + world.robot.radius_m + PERSON_PATH_MARGIN_M
        a, d = segs[:, :2], segs[:, 2:] - segs[:, :2]
        rel = xy[:, None, :] - a[None, :, :]
        t = np.clip(np.sum(rel * d[None], axis=2) / np.maximum(np.sum(d * d, axis=1), 1e-12)[None], 0.0, 1.0)
        near = np.hypot(*(rel - t[..., None] * d[None]).transpose(2, 0, 1)).min(axis=1)
        keep &= near > reach
    xy = xy[keep]
    cells = spec.to_cell(xy)
    reachable_cells = reachable(costmap, start)[cells[:, 0], cells[:, 1]]
    out: FloatArray = xy[reachable_cells]
    return out


# -- the run -------------------------------------------------------------------------------------------
@dataclass
class GoalResult:
    goal: tuple[float, float, float]
    status: str
    reason: str
    reached: bool
    error_m: float
    yaw_error_deg: float
    time_s: float
    driven_m: float
    shortest_m: float
    collisions: int
    clearance_m: float
    plans: int
    plan_ms: list[float] = field(default_factory=list)
    plan_cpu_ms: list[float] = field(default_factory=list)


@dataclass
class _Contact:
    walls: int = 0
    people: int = 0
    while_stopped: int = 0
    touching: bool = False
    # Each contact with a person as it began: who was moving towards whom, what the navigator was doing.
    people_log: list[dict[str, Any]] = field(default_factory=list)


def run_eval(
    world: World,
    goals: int,
    seed: int,
    config: NavConfig | None = None,
    on_goal: Callable[[GoalResult], None] | None = None,
    goal_list: Sequence[tuple[float, float, float | None]] | None = None,
    static_map: tuple[BoolArray, BoolArray] | None = None,
) -> dict[str, Any]:
    """Drive ``goals`` random goals (see the module docstring); the summary as a JSON-ready dict.
    ``on_goal`` is told each goal's result as it ends. ``goal_list``: drive these (x, y, yaw or None for
    any heading) in order instead (``eval deliver``); ``goals`` is then their number. ``static_map``: the
    navigator's map (occupied, unknown) on the walls' grid instead of the walls rasterized (``eval deliver
    --explore``: the map an exploration built)."""
    from agent.slam.pose import between, compose
    from agent.slam.simlog import TICK_S, simulated_sensors
    from drivers.sim.raycast import distance_to_segments, walls_array

    robot = world.robot
    if config is None:
        config = NavConfig(
            radius_m=robot.radius_m,
            track_m=robot.track_m,
            max_wheel_speed_mps=robot.max_wheel_radps * robot.wheel_radius_m,
        )
    sensors = simulated_sensors(world, seed)
    rng, clock, sim, geometry = sensors.rng, sensors.clock, sensors.sim, sensors.geometry
    scanner, odometry, fixes = sensors.scanner, sensors.odometry, sensors.fixes
    spec, occupied = rasterize_walls(world, config.resolution_m)
    if static_map is None:
        costmap = Costmap(spec, occupied, np.zeros(spec.shape, dtype=bool), config)
    else:
        costmap = Costmap(spec, static_map[0], static_map[1], config)
    mount = robot.laser_mount
    navigator = Navigator(config, costmap, (mount.x_m, mount.y_m, mount.yaw_rad))
    shortest = ShortestPaths(spec, occupied, robot.radius_m)
    segments = walls_array(world.walls)
    min_m, max_m = world.laser.min_range_mm / 1000.0, world.laser.max_range_mm / 1000.0
    scan_every = max(round(60.0 / world.laser.scan_rpm / TICK_S), 1)
    fix_every = max(round(1.0 / fixes.rate_hz / TICK_S), 1)

    start = robot.start
    estimate = np.array([start.x_m, start.y_m, start.yaw_rad])
    last_odometry = odometry.pose.copy()
    results: list[GoalResult] = []
    contact = _Contact()
    tick = 0
    position = (start.x_m, start.y_m)
    wall_start = time.perf_counter()
    for k in range(len(goal_list) if goal_list is not None else goals):
        gyaw: float | None
        if goal_list is not None:
            gx, gy, gyaw = goal_list[k]
        else:
            free = Costmap(spec, occupied, np.zeros(spec.shape, bool), config)
            candidates = goal_cells(world, free, position)
            far = candidates[np.hypot(*(candidates - np.array(position)).T) >= MIN_GOAL_DISTANCE_M]
            if not len(far):
                break
            gx, gy = far[rng.integers(len(far))]
            gyaw = float(rng.uniform(-math.pi, math.pi))
        truth = sim.pose()
        shortest_m = shortest.length_m((truth.x_m, truth.y_m), (float(gx), float(gy)))
        goal = Goal(float(gx), float(gy), gyaw)
        t_goal = clock.t_s
        navigator.set_goal(goal, t_goal)
        budget_s = 60.0 + 5.0 * shortest_m / config.max_speed_mps
        driven = 0.0
        clearance = math.inf
        collisions_before = contact.walls + contact.people
        last = (truth.x_m, truth.y_m)
        people_then = [sim.person_position(p) for p in world.people]
        while True:
            tick += 1
            clock.t_s = tick * TICK_S
            truth = sim.pose()
            driven += math.hypot(truth.x_m - last[0], truth.y_m - last[1])
            last = (truth.x_m, truth.y_m)
            # Contact with walls and people, on the truth.
            gap = distance_to_segments(last, segments) - robot.radius_m
            touching_person = False
            people_now = [sim.person_position(p) for p in world.people]
            for i, person in enumerate(world.people):
                px, py = people_now[i]
                person_gap = math.hypot(px - last[0], py - last[1]) - person.radius_m - robot.radius_m
                gap = min(gap, person_gap)
                if person_gap <= 0.0 and not contact.touching:
                    contact.people_log.append(
                        _contact_record(sim, navigator, person.name, people_then[i], people_now[i], clock.t_s)
                    )
                touching_person |= person_gap <= 0.0
            people_then = people_now
            clearance = min(clearance, gap)
            touching = gap <= 0.0
            if touching and not contact.touching:
                if touching_person:
                    contact.people += 1
                else:
                    contact.walls += 1
                if abs(navigator.monitor.command.v_mps) < 1e-6:
                    contact.while_stopped += 1
            contact.touching = touching
            # Localization: odometry, corrected by VLP fixes.
            odometry.update(sim.wheels().position_rad)
            estimate = compose(estimate, between(last_odometry, odometry.pose))
            last_odometry = odometry.pose.copy()
            if tick % fix_every == 0:
                got = fixes(sim, clock.t_s, odometry.pose)
                if not isinstance(got, str):
                    fix = got[1]
                    estimate[0] += FIX_GAIN * (fix.x_m - estimate[0])
                    estimate[1] += FIX_GAIN * (fix.y_m - estimate[1])
                    if fix.yaw_rad is not None:
                        estimate[2] += FIX_GAIN * math.remainder(fix.yaw_rad - estimate[2], math.tau)
            pose = (float(estimate[0]), float(estimate[1]), float(estimate[2]))
            if tick % scan_every == 0:
                ranges = scanner.ranges(clock.t_s)
                command = navigator.on_scan(clock.t_s, pose, geometry.angles_rad, ranges, min_m, max_m)
                sim.set_body_velocity(command.v_mps, command.omega_radps)
            if tick % CONTROL_EVERY == 0:
                out = navigator.step(clock.t_s, pose)
                sim.set_body_velocity(out.command.v_mps, out.command.omega_radps)
                if out.status in (NavStatus.REACHED, NavStatus.FAILED):
                    break
                if clock.t_s - t_goal > budget_s:
                    navigator.cancel(f"not there within the evaluation's {budget_s:.0f} s")
                    break
        sim.set_body_velocity(0.0, 0.0)
        truth = sim.pose()
        error = math.hypot(truth.x_m - goal.x_m, truth.y_m - goal.y_m)
        yaw_error = 0.0 if gyaw is None else abs(math.degrees(math.remainder(truth.yaw_rad - gyaw, math.tau)))
        plan_ms = [p.plan_ms for p in navigator.plans if p.searched]
        plan_cpu_ms = [p.cpu_ms for p in navigator.plans if p.searched]
        results.append(
            GoalResult(
                (goal.x_m, goal.y_m, math.nan if gyaw is None else gyaw),
                navigator.status.value,
                navigator.reason,
                navigator.status is NavStatus.REACHED and error <= REACHED_M and yaw_error <= REACHED_DEG,
                error,
                yaw_error,
                clock.t_s - t_goal,
                driven,
                shortest_m,
                contact.walls + contact.people - collisions_before,
                clearance,
                len(navigator.plans),
                plan_ms,
                plan_cpu_ms,
            )
        )
        position = (truth.x_m, truth.y_m)
        if on_goal is not None:
            on_goal(results[-1])
    return _summary(world, seed, results, contact, time.perf_counter() - wall_start, clock.t_s)


def _contact_record(
    sim: Any,
    navigator: Navigator,
    name: str,
    person_then: tuple[float, float],
    person_now: tuple[float, float],
    t_s: float,
) -> dict[str, Any]:
    """Who closed the gap at a contact: each one's speed along the line between them (m/s, > 0 towards
    the other), and the navigator's state then."""
    from agent.slam.simlog import TICK_S

    truth = sim.pose()
    v_robot = sim.body_motion()[0]
    ux, uy = person_now[0] - truth.x_m, person_now[1] - truth.y_m
    norm = max(math.hypot(ux, uy), 1e-9)
    ux, uy = ux / norm, uy / norm
    robot_closing = v_robot * (math.cos(truth.yaw_rad) * ux + math.sin(truth.yaw_rad) * uy)
    pvx = (person_now[0] - person_then[0]) / TICK_S
    pvy = (person_now[1] - person_then[1]) / TICK_S
    person_closing = -(pvx * ux + pvy * uy)
    cost = navigator.costmap.cost_at(np.array([[truth.x_m, truth.y_m]]))[0]
    action = navigator.recovery.action
    return {
        "t_s": _r(t_s, 2),
        "person": name,
        "robot_speed_mps": _r(v_robot),
        "robot_closing_mps": _r(robot_closing),
        "person_speed_mps": _r(math.hypot(pvx, pvy)),
        "person_closing_mps": _r(person_closing),
        "navigator": navigator.status.value,
        "recovery": action.value if action is not None else None,
        "monitor_stopped": navigator.monitor.command.v_mps == 0.0,
        "in_predicted_sweep": not bool(np.isfinite(cost)),
        "moving_tracks": len(navigator.moving.moving()),
    }


def _summary(
    world: World, seed: int, results: list[GoalResult], contact: _Contact, wall_s: float, sim_s: float
) -> dict[str, Any]:
    reached = [r for r in results if r.reached]
    ratios = [
        r.driven_m / r.shortest_m for r in reached if r.shortest_m > 0.0 and math.isfinite(r.shortest_m)
    ]
    plan_ms = [ms for r in results for ms in r.plan_ms]
    plan_cpu_ms = [ms for r in results for ms in r.plan_cpu_ms]
    return {
        "world": world.name,
        "seed": seed,
        "people_yield": [p.name for p in world.people if p.yields],
        "goals": len(results),
        "reached": len(reached),
        "success_rate": round(len(reached) / len(results), 4) if results else None,
        "collisions": contact.walls + contact.people,
        "collisions_walls": contact.walls,
        "collisions_people": contact.people,
        "collisions_while_stopped": contact.while_stopped,
        "contacts_people": contact.people_log,
        "path_ratio_median": _r(np.median(ratios)) if ratios else None,
        "path_ratio_max": _r(max(ratios)) if ratios else None,
        "final_error_m_median": _r(np.median([r.error_m for r in reached]), 4) if reached else None,
        "final_error_m_max": _r(max(r.error_m for r in reached), 4) if reached else None,
        "yaw_error_deg_median": _r(np.median([r.yaw_error_deg for r in reached]), 2) if reached else None,
        "yaw_error_deg_max": _r(max(r.yaw_error_deg for r in reached), 2) if reached else None,
        "time_s_median": _r(np.median([r.time_s for r in reached]), 1) if reached else None,
        "time_s_total": _r(sum(r.time_s for r in results), 1),
        "clearance_m_min": _r(min(r.clearance_m for r in results), 4) if results else None,
        "plans": sum(r.plans for r in results),
        "searches": len(plan_ms),
        "plan_ms_median": _r(np.median(plan_ms), 2) if plan_ms else None,
        "plan_ms_p95": _r(np.percentile(plan_ms, 95), 2) if plan_ms else None,
        "plan_cpu_ms_median": _r(np.median(plan_cpu_ms), 2) if plan_cpu_ms else None,
        "failures": [
            {
                "goal": [_r(v, 3) for v in r.goal],
                "status": r.status,
                "reason": r.reason,
                "error_m": _r(r.error_m, 3),
            }
            for r in results
            if not r.reached
        ],
        "sim_s": _r(sim_s, 1),
        "wall_s": _r(wall_s, 1),
        "realtime_factor": _r(sim_s / wall_s, 1) if wall_s > 0 else None,
        "map_source": "truth: the world's walls rasterized at the costmap's resolution (a finished SLAM "
        "map); people and other changes only through the scans",
        "localization": "wheel odometry corrected by simulated VLP fixes (10 Hz, 5 mm, 0.3 deg, constant "
        f"gain {FIX_GAIN})",
    }


def _r(value: Any, digits: int = 3) -> float | None:
    number = float(value)
    return round(number, digits) if math.isfinite(number) else None


def run(args: argparse.Namespace) -> int:
    from drivers.errors import ConfigError
    from drivers.sim.worldfile import load_world

    if args.goals < 1:
        raise ConfigError("--goals", "must be at least 1")
    from agent.commands.worlds import resolve_world

    path = resolve_world(args.world)
    world = load_world(path)
    if args.people_never_yield:
        world = dataclasses.replace(
            world, people=tuple(dataclasses.replace(p, yields=False) for p in world.people)
        )
    progress = None
    if args.progress:

        def progress(r: GoalResult) -> None:
            line = {
                "goal": [_r(v, 3) for v in r.goal],
                "reached": r.reached,
                "status": r.status,
                "collisions": r.collisions,
                "ratio": _r(r.driven_m / r.shortest_m) if r.shortest_m > 0 else None,
                "time_s": _r(r.time_s, 1),
            }
            print(json.dumps(line), file=sys.stderr, flush=True)

    summary = run_eval(world, args.goals, args.seed, on_goal=progress)
    if args.json:
        print(json.dumps(summary, sort_keys=True))
        return 0
    s = summary
    print(f"vlp-agent eval nav: {path}, {s['goals']} goals, seed {s['seed']}")
    print(f"  reached            {s['reached']}/{s['goals']} within {REACHED_M} m and {REACHED_DEG:g} deg")
    print(
        f"  collisions         {s['collisions']} (walls {s['collisions_walls']}, people "
        f"{s['collisions_people']}); closest approach {s['clearance_m_min']} m"
    )
    print(f"  path / shortest    median {s['path_ratio_median']}, max {s['path_ratio_max']}")
    print(
        f"  final error        median {s['final_error_m_median']} m, {s['yaw_error_deg_median']} deg; "
        f"max {s['final_error_m_max']} m, {s['yaw_error_deg_max']} deg"
    )
    print(
        f"  planning           {s['searches']} searches, median {s['plan_ms_median']} ms "
        f"({s['plan_cpu_ms_median']} ms CPU), p95 {s['plan_ms_p95']} ms"
    )
    print(
        f"  time               {s['time_s_total']} s simulated, {s['wall_s']} s wall "
        f"({s['realtime_factor']}x)"
    )
    for failure in s["failures"]:
        print(
            f"  failed             {failure['goal']}: {failure['status']} {failure['reason']}",
            file=sys.stdout,
        )
    return 0
