"""The simulated office without VLP, seed by seed: issue 20's acceptance (ATE <= 3 cm for 24 of 24 seeds).

Per seed, what ``vlp-agent eval slam --world examples/worlds/office.toml --seed S`` runs: the 5-minute
drive with the world's laser and wheel errors, the odometry of a robot through ``calibrate wheels``
(``--wheels nominal``: the design's geometry), the filter at the eval's settings (30 particles, the
simulated robot's motion model). One JSON object per seed (``ate_m``: RMS position error against the
truth, no alignment; ``ate_aligned_m``; ``ate_max_m``; ``ate_mean_m``, the same for the weighted mean of the
final particles' ancestries, ``RbpfSlam.mean_trajectory``; ``odometry_ate_m``; resamplings, match failures,
loop closures, wall and CPU seconds), then a summary per group of seeds: ``--tune`` seeds (default 0-5,
where knobs were tuned) and the others (where they were not), each with mean, median, worst and how many
are over ``--budget`` (3 cm).

``--people`` changes the world's people: ``yield`` (the world's: pedestrians stop for the robot and stand
until it has passed), ``walk`` (they never stop), ``none`` (no people): the measure of how much people in
view cost the map.

    python benchmarks/slam_office.py --seeds 0 1 2 3 4 5
    python benchmarks/slam_office.py --seeds $(seq 0 23) --out office.json
    python benchmarks/slam_office.py --seeds 0 1 2 --people none --seconds 60 --wheels nominal
    python benchmarks/slam_office.py --seeds $(seq 8 23) --tune 0 1 2 3 4 5 6 7 --degenerate-noise-scale 1
    python benchmarks/slam_office.py --seeds 0 1 2 3 4 5 --edge-sigma 0.005 0.005 0.001 --match-sigma 0.1
    python benchmarks/slam_office.py --seeds 10 14 18 22 --loop-hypotheses 0
    python benchmarks/slam_office.py --seeds $(seq 0 23) --medial-window-cells 3
    python benchmarks/slam_office.py --seeds 0 1 2 3 --grid-phase fixed --grid-offset 0.0125
    python benchmarks/slam_office.py --seeds 0 1 2 3 4 5 6 7 --grid-turn 30
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import resource
import statistics
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agent.commands.eval_slam import FINAL_SCAN_CHAIN, front_end, log_proposal
from agent.slam.loops import LoopClosureConfig
from agent.slam.metrics import absolute_trajectory_error, aligned_trajectory_error
from agent.slam.pose import compose, inverse
from agent.slam.proposal import ProposalConfig
from agent.slam.rbpf import RbpfConfig
from agent.slam.replay import replay
from agent.slam.simlog import (
    MOTION_NOISE,
    WheelErrorModel,
    WheelGeometry,
    simulate_log,
    wheel_calibration_runs,
)
from calibration.wheels import Run as WheelRun
from calibration.wheels import fit_wheels
from drivers.sim.world import World
from drivers.sim.worldfile import load_world

OFFICE = Path(__file__).resolve().parents[1] / "examples" / "worlds" / "office.toml"


def with_people(world: World, people: str) -> World:
    if people == "yield":
        return world
    if people == "none":
        return dataclasses.replace(world, people=())
    walkers = tuple(dataclasses.replace(p, yields=False) for p in world.people)
    return dataclasses.replace(world, people=walkers)


def loop_config(
    edge_sigma: tuple[float, float, float] | None,
    match_sigma: float | None,
    edge_match_sigma: float | None = None,
    hypotheses: int | None = None,
) -> LoopClosureConfig:
    """The loop closure's defaults with the pose graph's edge sigmas, loop-factor covariance,
    front-end edges from the match's information (``edge_match_sigma_m``) and the known-area rule
    (``hypotheses``) set."""
    config = LoopClosureConfig()
    if not FINAL_SCAN_CHAIN["simulated"]:  # as eval slam --world runs the simulated robot
        config = dataclasses.replace(config, final_scan_chain=None)
    if hypotheses is not None:
        config = dataclasses.replace(config, hypotheses=hypotheses)
    if edge_match_sigma is not None:
        config = dataclasses.replace(config, edge_match_sigma_m=edge_match_sigma)
    if edge_sigma is not None:
        config = dataclasses.replace(config, motion_sigma=edge_sigma)
    if match_sigma is not None:
        config = dataclasses.replace(config, match_sigma_m=match_sigma)
    return config


def run_seed(
    world: World,
    seed: int,
    seconds: float,
    wheels: str,
    loop_closure: bool = True,
    edge_sigma: tuple[float, float, float] | None = None,
    match_sigma: float | None = None,
    degenerate_scale: float | None = None,
    particles: int = 30,
    grid_offset: float = 0.0,
    free_margin: float | None = None,
    edge_match_sigma: float | None = None,
    hypotheses: int | None = None,
    medial_window: int | None = None,
    grid_phase: str | None = None,
    grid_turn_deg: float = 0.0,
) -> dict[str, Any]:
    errors = WheelErrorModel()
    geometry = None
    if wheels == "calibrated":
        runs = wheel_calibration_runs(world, errors, np.random.default_rng(seed))
        fit = fit_wheels([WheelRun(*r) for r in runs])
        geometry = WheelGeometry(fit.wheel_radius_m, fit.track_m)
    simulated = simulate_log(world, seconds, wheel_errors=errors, wheel_geometry=geometry, seed=seed)
    # The filter's frame: the world's turned by grid_turn_deg about its origin, then moved by grid_offset in
    # x and y (walls oblique to the lattice, or off its boundaries); its poses are moved back for the ATE.
    frame = np.array([grid_offset, grid_offset, math.radians(grid_turn_deg)])
    proposal = log_proposal("simulated", ProposalConfig())
    if degenerate_scale is not None:
        proposal = dataclasses.replace(proposal, degenerate_noise_scale=degenerate_scale)
    if medial_window is not None:
        proposal = dataclasses.replace(
            proposal, matcher=dataclasses.replace(proposal.matcher, medial_window_cells=medial_window)
        )
    config = RbpfConfig(
        particles=particles,
        noise=MOTION_NOISE,
        proposal=proposal,
        initial_pose=tuple(compose(frame, np.asarray(simulated.start_pose(from_fix=False)))),
        free_margin_m=free_margin,
        seed=seed,
        grid_phase_from_walls=(
            RbpfConfig().grid_phase_from_walls if grid_phase is None else grid_phase == "walls"
        ),
        loop_closure=(
            loop_config(edge_sigma, match_sigma, edge_match_sigma, hypotheses) if loop_closure else None
        ),
    )
    t0, c0 = time.perf_counter(), time.process_time()
    result = replay(simulated.log, config)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    back = inverse(frame)
    result = dataclasses.replace(
        result, poses=compose(back, result.poses), mean_poses=compose(back, result.mean_poses)
    )
    truth = simulated.truth[: len(simulated.log)]
    error = np.hypot(*(result.poses[:, :2] - truth[:, :2]).T)
    stats = result.slam.stats
    return {
        "seed": seed,
        "ate_m": round(absolute_trajectory_error(truth, result.poses), 4),
        "ate_aligned_m": round(aligned_trajectory_error(truth, result.poses), 4),
        "ate_max_m": round(float(error.max()), 4),
        "ate_mean_m": round(absolute_trajectory_error(truth, result.mean_poses), 4),
        "odometry_ate_m": round(absolute_trajectory_error(truth, simulated.odometry_in_world()), 4),
        "updates": stats.updates,
        "resamples": stats.resamples,
        "match_failures": stats.match_failures,
        "loop_closures": stats.loop_closures,
        "loop_rebuilds": stats.loop_rebuilds,
        "loop_verdicts": dict(sorted(stats.loop_verdicts.items())),
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
    }


def summary(rows: list[dict[str, Any]], budget: float) -> dict[str, Any]:
    ate = [r["ate_m"] for r in rows]
    if not ate:
        return {"seeds": 0}
    return {
        "seeds": len(ate),
        "ate_m_mean": round(statistics.fmean(ate), 4),
        "ate_m_median": round(statistics.median(ate), 4),
        "ate_m_max": max(ate),
        "worst_seed": rows[int(np.argmax(ate))]["seed"],
        "over_budget": sum(a > budget for a in ate),
        "ate_aligned_m_mean": round(statistics.fmean(r["ate_aligned_m"] for r in rows), 4),
        # The same over the weighted mean of the final particles' ancestries (RbpfSlam.mean_trajectory).
        "ate_mean_m_mean": round(statistics.fmean(r["ate_mean_m"] for r in rows), 4),
        "ate_mean_m_max": max(r["ate_mean_m"] for r in rows),
        "ate_mean_over_budget": sum(r["ate_mean_m"] > budget for r in rows),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--world", type=Path, default=OFFICE)
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(6)))
    parser.add_argument("--tune", type=int, nargs="*", default=list(range(6)), help="seeds tuned on")
    parser.add_argument("--seconds", type=float, default=300.0)
    parser.add_argument("--wheels", choices=("calibrated", "nominal"), default="calibrated")
    parser.add_argument("--people", choices=("yield", "walk", "none"), default="yield")
    parser.add_argument("--loop-closure", choices=("on", "off"), default="on")
    parser.add_argument(
        "--edge-sigma",
        type=float,
        nargs=3,
        metavar=("X", "Y", "YAW"),
        help="the pose graph's front-end edge sigmas (LoopClosureConfig.motion_sigma)",
    )
    parser.add_argument("--match-sigma", type=float, help="loop factors with the match's covariance")
    parser.add_argument(
        "--edge-match-sigma",
        type=float,
        metavar="S",
        help="front-end edges from each update's scan match information "
        "(LoopClosureConfig.edge_match_sigma_m)",
    )
    parser.add_argument(
        "--degenerate-noise-scale",
        type=float,
        help="ProposalConfig.degenerate_noise_scale (default: eval slam's for the simulated robot; 1: off)",
    )
    parser.add_argument(
        "--grid-offset",
        type=float,
        default=0.0,
        metavar="M",
        help="start the map M metres off the world's origin in x and y (poses moved back before the ATE): "
        "the office's walls all lie on 5 cm boundaries, which with an unmoved 5 cm lattice are the worst "
        "case (--grid-phase fixed); with the lattice fitted to the walls the offset changes nothing "
        "(default 0: the office as issue 20 measures it)",
    )
    parser.add_argument(
        "--grid-turn",
        type=float,
        default=0.0,
        metavar="DEG",
        help="start the map in a frame turned DEG degrees about the world's origin (poses turned back before "
        "the ATE): the office's walls then run oblique to the lattice, as in a building whose map frame is "
        "not along its walls (default 0)",
    )
    parser.add_argument(
        "--free-margin",
        type=float,
        metavar="M",
        help="RbpfConfig.free_margin_m: a beam's free space stops M short of its endpoint "
        "(default: eval slam's for the simulated robot)",
    )
    parser.add_argument(
        "--loop-hypotheses",
        type=int,
        metavar="N",
        help="LoopClosureConfig.hypotheses: the known-area rule's best coarse poses per window, where the"
        f" coarse tests find nothing (0: off; default the config's, {LoopClosureConfig().hypotheses})",
    )
    parser.add_argument(
        "--medial-window-cells",
        type=int,
        metavar="W",
        help="MatcherConfig.medial_window_cells: a wall's straightness judged over the square of W cells "
        "either way (default: eval slam's for the simulated robot, 0: a wall cell's four neighbours)",
    )
    parser.add_argument(
        "--grid-phase",
        choices=("walls", "fixed"),
        help="RbpfConfig.grid_phase_from_walls: the lattice moved at the first scan so that its walls run "
        "through cell centres, or left where the grid puts it (default: eval slam's for the simulated robot)",
    )
    parser.add_argument("--particles", type=int, default=30, help="RbpfConfig.particles (the agent's 30)")
    parser.add_argument("--budget", type=float, default=0.03, help="metres (issue 20: 3 cm)")
    parser.add_argument("--out", type=Path, help="also write the whole result here as JSON")
    args = parser.parse_args()
    world = with_people(load_world(args.world), args.people)
    rows = []
    for seed in args.seeds:
        edge = tuple(args.edge_sigma) if args.edge_sigma else None
        row = run_seed(
            world,
            seed,
            args.seconds,
            args.wheels,
            args.loop_closure == "on",
            edge,
            args.match_sigma,
            args.degenerate_noise_scale,
            args.particles,
            args.grid_offset,
            args.free_margin if args.free_margin is not None else front_end("simulated").free_margin_m,
            args.edge_match_sigma,
            args.loop_hypotheses,
            args.medial_window_cells,
            args.grid_phase,
            args.grid_turn,
        )
        rows.append(row)
        print(json.dumps(row), flush=True)
    tuned = [r for r in rows if r["seed"] in args.tune]
    other = [r for r in rows if r["seed"] not in args.tune]
    result = {
        "world": str(args.world),
        "people": args.people,
        "wheels": args.wheels,
        "seconds": args.seconds,
        "loop_closure": args.loop_closure,
        "edge_sigma": args.edge_sigma,
        "match_sigma": args.match_sigma,
        "loop_hypotheses": args.loop_hypotheses,
        "edge_match_sigma": args.edge_match_sigma,
        "degenerate_noise_scale": args.degenerate_noise_scale,
        "particles": args.particles,
        "grid_offset_m": args.grid_offset,
        "grid_turn_deg": args.grid_turn,
        "free_margin_m": args.free_margin,
        "medial_window_cells": args.medial_window_cells,
        "grid_phase": args.grid_phase,
        "budget_m": args.budget,
        "tuned": summary(tuned, args.budget),
        "not_tuned": summary(other, args.budget),
        "all": summary(rows, args.budget),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
        "runs": rows,
    }
    if args.out:
        args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "runs"}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
