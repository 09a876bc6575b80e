"""Issue 21's lifelong-mapping acceptance: map the office's west half, stop, start again with the saved map,
map the east half: one consistent map. Prints one JSON object.

    python benchmarks/map_continue.py [--seconds 180] [--vlp-fixes] [--start-error-m 0.0] [--seed 0]

One simulated drive of the office route (``agent.slam.simlog``: the world's laser model, wheels that err;
with ``--vlp-fixes``, modelled VLP fixes) is cut where the robot first crosses x = 10 m, the middle of the
building: the first run (the corridor's west part and room S2) maps from the start; its map goes to disk
and back as map_server files (``agent.slam.mapio``, what the agent writes); the second run, a new filter,
is seeded with it (``[slam] mode = "continue"``: ``RbpfSlam.seed_map``) and starts at the true pose at the
cut plus ``--start-error-m`` in x (the start pose the robot is given), then drives the rest: S3 and N3 in
the east, then back west through N2 and the corridor, over what the first run mapped.

Reported: ``ate_m`` over both runs together (each run's trajectory along its final best particle, as
``eval slam`` scores it) and ``ate_online_m`` (the pose each filter reported as it went), each run's own,
the same drive mapped in one go for comparison (``one_run_ate_m``), and ``first_map_kept``: the share of
the first map's occupied cells still occupied in the final map (1.0: the east run did not move the west).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from agent.runtime.mapper import prior_log_odds  # noqa: E402
from agent.slam.grid import LogOddsModel  # noqa: E402
from agent.slam.mapio import load_map, save_map  # noqa: E402
from agent.slam.metrics import absolute_trajectory_error  # noqa: E402
from agent.slam.rbpf import RbpfConfig  # noqa: E402
from agent.slam.render import OccupancyImage, occupancy_image  # noqa: E402
from agent.slam.replay import ReplayResult, replay  # noqa: E402
from agent.slam.simlog import MOTION_NOISE, VlpFixModel, simulate_log  # noqa: E402
from drivers.sim.worldfile import load_world  # noqa: E402

OFFICE = REPO / "agent" / "examples" / "worlds" / "office.toml"
MIDDLE_X_M = 10.0


def occupied_cells(image: OccupancyImage) -> set[tuple[int, int]]:
    rows, cols = np.nonzero(image.pixels == 0)
    x = round(image.origin[0] / image.resolution_m) + cols
    y = round(image.origin[1] / image.resolution_m) + (image.pixels.shape[0] - 1 - rows)
    return set(zip(x.tolist(), y.tolist(), strict=True))


def final_map(result: ReplayResult) -> OccupancyImage:
    window = result.slam.map_window()
    assert window is not None
    return occupancy_image(window[0], window[1], 0.05)


def measure(seconds: float, vlp_fixes: bool, start_error_m: float, seed: int, folder: Path) -> dict[str, Any]:
    t0 = time.perf_counter()
    drive = simulate_log(load_world(OFFICE), seconds, fixes=VlpFixModel() if vlp_fixes else None, seed=seed)
    truth = drive.truth
    crossed = np.flatnonzero(truth[:, 0] > MIDDLE_X_M)
    if crossed.size == 0:
        raise ValueError(f"the drive never reaches x = {MIDDLE_X_M} m: give it more --seconds")
    cut = int(crossed[0])
    records = drive.log.records
    west_log = dataclasses.replace(drive.log, records=records[:cut])
    east_log = dataclasses.replace(drive.log, records=records[cut:])
    cut_t_s = records[cut].t_s
    west_fixes = tuple(f for f in drive.fixes if f.t_s < cut_t_s)
    east_fixes = tuple(f for f in drive.fixes if f.t_s >= cut_t_s)

    def config(start: tuple[float, float, float]) -> RbpfConfig:
        return RbpfConfig(particles=30, noise=MOTION_NOISE, initial_pose=start, seed=seed)

    west = replay(west_log, config(drive.start_pose(from_fix=vlp_fixes)), fixes=west_fixes)
    files = save_map(final_map(west), folder / "map.yaml", comment="benchmarks/map_continue.py west run")
    saved = load_map(files.yaml)
    log_odds, origin = prior_log_odds(saved, LogOddsModel())
    start = (float(truth[cut, 0]) + start_error_m, float(truth[cut, 1]), float(truth[cut, 2]))
    east = replay(east_log, config(start), fixes=east_fixes, prior=(log_odds.astype(np.float32), origin))
    whole = replay(drive.log, config(drive.start_pose(from_fix=vlp_fixes)), fixes=drive.fixes)

    both = np.vstack([west.poses, east.poses])
    both_online = np.vstack([west.online_poses, east.online_poses])
    first = occupied_cells(saved)
    last = occupied_cells(final_map(east))
    return {
        "seconds": seconds,
        "vlp_fixes": vlp_fixes,
        "seed": seed,
        "start_error_m": start_error_m,
        "cut_record": cut,
        "cut_t_s": round(cut_t_s - records[0].t_s, 2),
        "records": len(records),
        "distance_m": round(drive.distance_m, 2),
        "west_x_max_m": round(float(truth[:cut, 0].max()), 2),
        "east_x_range_m": [round(float(truth[cut:, 0].min()), 2), round(float(truth[cut:, 0].max()), 2)],
        "ate_m": round(absolute_trajectory_error(truth, both), 4),
        "ate_online_m": round(absolute_trajectory_error(truth, both_online), 4),
        "west_ate_m": round(absolute_trajectory_error(truth[:cut], west.poses), 4),
        "east_ate_m": round(absolute_trajectory_error(truth[cut:], east.poses), 4),
        "one_run_ate_m": round(absolute_trajectory_error(truth, whole.poses), 4),
        "odometry_ate_m": round(absolute_trajectory_error(truth, drive.odometry_in_world()), 4),
        "first_map_occupied_cells": len(first),
        "first_map_kept": round(len(first & last) / max(len(first), 1), 4),
        "wall_s": round(time.perf_counter() - t0, 1),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=180.0, help="simulated drive (the route is ~3 min)")
    parser.add_argument("--vlp-fixes", action="store_true", help="modelled VLP fixes weigh the particles")
    parser.add_argument("--start-error-m", type=float, default=0.0, help="the second run's start pose error")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="map-continue-") as tmp:
        result = measure(args.seconds, args.vlp_fixes, args.start_error_m, args.seed, Path(tmp))
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
