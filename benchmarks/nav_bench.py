"""Speed of the navigation's hot parts on the office world; prints one JSON object.

* ``plan``: a global plan on the office map at 0.05 m (the world's walls rasterized: 420 x 260 cells)
  between random reachable start and goal cells, each a fresh search (the costmap's version is bumped,
  as a scan that changed the obstacles would): ``plan_ms_*`` wall time, ``plan_cpu_ms_median`` this
  thread's CPU time; ``costmap_ms_median`` re-deriving the inflated cost grid after a change (the
  distance transform), ``replan_ms_median`` both together (what a replan after an obstacle change costs).
* ``collision``: the collision monitor on 682-beam URG scans cast in the office at random poses:
  ``collision_ms_median``/``_max`` per scan; ``obstacle_layer_ms_median`` marking and clearing the
  costmap's obstacle layer with the same scans.

Budgets (ARCHITECTURE.md, issue 18): plan <= 20 ms median on one core; collision monitor <= 2 ms per scan.
OpenCV and BLAS are held to one thread; a machine busy with other work inflates the wall times (compare
the CPU times).

    python benchmarks/nav_bench.py [--plans 50] [--scans 300] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agent.commands.eval_nav import rasterize_walls
from agent.navigation.collision import CollisionMonitor
from agent.navigation.config import NavConfig
from agent.navigation.costmap import Costmap
from agent.navigation.planner import GlobalPlanner
from agent.slam.simlog import laser_geometry
from drivers.sim.raycast import cast_rays, walls_array
from drivers.sim.worldfile import load_world

OFFICE = Path(__file__).resolve().parents[1] / "examples" / "worlds" / "office.toml"


def _median(values: list[float]) -> float:
    return round(float(np.median(values)), 3)


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--world", default=str(OFFICE))
    parser.add_argument("--plans", type=int, default=50)
    parser.add_argument("--scans", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    rng = np.random.default_rng(args.seed)
    world = load_world(args.world)
    config = NavConfig()
    spec, occupied = rasterize_walls(world, config.resolution_m)
    costmap = Costmap(spec, occupied, np.zeros(spec.shape, dtype=bool), config)
    free = np.argwhere(costmap.distance_m() >= config.radius_m + 0.3)
    planner = GlobalPlanner(config.clearance_weight)
    plan_ms: list[float] = []
    plan_cpu: list[float] = []
    costmap_ms: list[float] = []
    replan_ms: list[float] = []
    lengths: list[float] = []
    while len(plan_ms) < args.plans:
        a, b = spec.to_world(free[rng.integers(len(free), size=2)])
        costmap.version += 1  # as after a scan that changed the obstacles
        t0 = time.perf_counter()
        costmap.cost()
        t1 = time.perf_counter()
        plan = planner.plan(costmap, (float(a[0]), float(a[1])), (float(b[0]), float(b[1])))
        t2 = time.perf_counter()
        if not plan.ok or plan.length_m < 1.0:
            continue
        costmap_ms.append((t1 - t0) * 1e3)
        plan_ms.append(plan.plan_ms)
        plan_cpu.append(plan.cpu_ms)
        replan_ms.append((t2 - t0) * 1e3)
        lengths.append(plan.length_m)

    walls = walls_array(world.walls)
    people = np.array([(*p.path[0], p.radius_m) for p in world.people]).reshape(-1, 3)
    geometry = laser_geometry(world)
    monitor = CollisionMonitor(config)
    min_m, max_m = world.laser.min_range_mm / 1000.0, world.laser.max_range_mm / 1000.0
    collision_ms: list[float] = []
    collision_cpu: list[float] = []
    layer_ms: list[float] = []
    for i in range(args.scans):
        x, y = spec.to_world(free[rng.integers(len(free))])[0]
        yaw = float(rng.uniform(-math.pi, math.pi))
        ranges = cast_rays((float(x), float(y)), geometry.angles_rad + yaw, walls, people, max_m)
        ranges = np.where(np.isfinite(ranges), ranges, 0.0)
        t0, c0 = time.perf_counter(), time.thread_time()
        monitor.on_scan(float(i), geometry.angles_rad, ranges, min_m, max_m)
        t1, c1 = time.perf_counter(), time.thread_time()
        costmap.update_scan((float(x), float(y), yaw), geometry.angles_rad, ranges, min_m, max_m)
        t2 = time.perf_counter()
        collision_ms.append((t1 - t0) * 1e3)
        collision_cpu.append((c1 - c0) * 1e3)
        layer_ms.append((t2 - t1) * 1e3)

    print(
        json.dumps(
            {
                "world": world.name,
                "grid_cells": list(spec.shape),
                "resolution_m": spec.resolution_m,
                "plans": len(plan_ms),
                "plan_length_m_median": _median(lengths),
                "plan_ms_median": _median(plan_ms),
                "plan_ms_p95": round(float(np.percentile(plan_ms, 95)), 3),
                "plan_cpu_ms_median": _median(plan_cpu),
                "costmap_ms_median": _median(costmap_ms),
                "replan_ms_median": _median(replan_ms),
                "scans": len(collision_ms),
                "beams": int(geometry.beams),
                "collision_ms_median": _median(collision_ms),
                "collision_ms_max": round(max(collision_ms), 3),
                "collision_cpu_ms_median": _median(collision_cpu),
                "obstacle_layer_ms_median": _median(layer_ms),
            },
            sort_keys=True,
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
