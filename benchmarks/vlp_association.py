"""VLP time per frame under a ceiling of densely repeated ids: the association's bound, measured.

The world is ``examples/worlds/dense_repeats.toml``: 120 LEDs 0.5 m apart with four signatures, twelve of
them in view (4 x 3) at 800x600. The robot stands near (0, 0.25) m, its lens circling 2 cm and its heading
swinging 2 degrees, so all twelve stay in view while their images move. Frames are rendered once; each
case runs a fresh pipeline over all of them and times every frame, the first (a whole-frame search, twelve
new tracks, no id settled) included:

- ``odometry_prior``: an odometry-grade prior on every frame (off by ~0.2 m and ~10 degrees, sigma 0.4 m and
  20 degrees, as ``vlp-agent eval vlp`` gives when driving): some fifteen candidates per LED, ~10^13
  combinations of twelve;
- ``no_prior``: no prior ever, so the pipeline never has a last fix either: every frame associates with all
  30 candidates per LED and the repeated pattern leaves the placement ambiguous (no fix, by design); this is
  the worst work the association can be asked for.

Per case: median and max time per frame (all frames, and steady frames after ``--warmup``; wall time, and
the thread's CPU time, which leaves out waiting for a core on a shared machine), the
association's work (candidate checks, assignments solved, frames whose budget ran out), fixes and the
largest error of a fix. One core (``cv2.setNumThreads(1)``). Prints one JSON object; target (issue 19):
max <= 20 ms per frame.

    .venv/bin/python benchmarks/vlp_association.py [--frames N] [--rounds R] [--seed S] [--warmup N]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agent.sim_view import agent_view
from agent.vlp.model import PosePrior, VlpFix
from agent.vlp.pipeline import VlpPipeline
from drivers.sim.render import RollingShutterRenderer
from drivers.sim.world import Pose2D
from drivers.sim.worldfile import load_world

WORLD = Path(__file__).resolve().parents[1] / "examples" / "worlds" / "dense_repeats.toml"
CENTRE = (0.0, 0.25)


def pose_at(t: float) -> Pose2D:
    """A 2 cm circle around ``CENTRE`` at 1 rad/s, the heading swinging 2 degrees."""
    return Pose2D(
        CENTRE[0] + 0.02 * math.cos(t), CENTRE[1] + 0.02 * math.sin(t), math.radians(2.0) * math.sin(0.7 * t)
    )


@dataclasses.dataclass
class Run:
    """One case's pass over the frames: per frame its time, association work and full LEDs; the fixes'
    errors."""

    times_ms: list[float] = dataclasses.field(default_factory=list)
    cpu_ms: list[float] = dataclasses.field(default_factory=list)
    checks: list[int] = dataclasses.field(default_factory=list)
    solved: list[int] = dataclasses.field(default_factory=list)
    leds: list[int] = dataclasses.field(default_factory=list)
    errors_m: list[float] = dataclasses.field(default_factory=list)
    truncated: int = 0


def run_case(
    frames: list[tuple[npt.NDArray[np.uint8], float, Pose2D]],
    prior_sigmas: tuple[float, float] | None,
    seed: int,
) -> Run:
    """A fresh pipeline over every frame; with ``prior_sigmas`` (xy, yaw) a prior on each frame, off from
    the truth by half those sigmas (random)."""
    view = agent_view(load_world(WORLD))
    pipeline = VlpPipeline(view.intrinsics, view.led_map, view.mount)
    rng = np.random.default_rng(seed)
    run = Run()
    for image, t, truth in frames:
        prior = None
        if prior_sigmas is not None:
            sxy, syaw = prior_sigmas
            prior = PosePrior(
                truth.x_m + float(rng.normal(0.0, 0.5 * sxy)),
                truth.y_m + float(rng.normal(0.0, 0.5 * sxy)),
                truth.yaw_rad + float(rng.normal(0.0, 0.5 * syaw)),
                sxy,
                syaw,
            )
        c0 = time.thread_time()
        t0 = time.perf_counter()
        result = pipeline.process(image, t, prior=prior)
        run.times_ms.append(1e3 * (time.perf_counter() - t0))
        run.cpu_ms.append(1e3 * (time.thread_time() - c0))
        run.checks.append(result.work.checks)
        run.solved.append(result.work.hypotheses)
        run.truncated += int(result.work.truncated)
        run.leds.append(sum(1 for o in result.leds if o.visibility == "full"))
        if isinstance(result, VlpFix):
            run.errors_m.append(math.hypot(result.x_m - truth.x_m, result.y_m - truth.y_m))
    return run


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60, help="frames per case and round (default 60)")
    parser.add_argument(
        "--rounds", type=int, default=3, help="rounds over both cases, interleaved (default 3)"
    )
    parser.add_argument("--warmup", type=int, default=5, help="frames not counted as steady (default 5)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.frames < 1 or args.rounds < 1 or not 0 <= args.warmup < args.frames:
        parser.error("--frames and --rounds must be >= 1, 0 <= --warmup < --frames")
    cv2.setNumThreads(1)
    world = load_world(WORLD)
    renderer = RollingShutterRenderer.for_world(world, seed=args.seed)
    fps = world.camera.frame_rate_hz
    frames = []
    for k in range(args.frames):
        rendered = renderer.render(pose_at, 100.0 + k / fps)
        frames.append((rendered.image.copy(), rendered.truth.t_mid_s, rendered.truth.base_pose))
    cases = {"odometry_prior": (0.4, math.radians(20.0)), "no_prior": None}
    runs: dict[str, list[Run]] = {name: [] for name in cases}
    for r in range(args.rounds):
        for name, sigmas in cases.items():
            runs[name].append(run_case(frames, sigmas, args.seed + r))
    report: dict[str, object] = {
        "world": world.name,
        "image_size_px": [world.camera.output_width_px, world.camera.output_height_px],
        "frames": args.frames,
        "rounds": args.rounds,
        "target_frame_ms_max": 20.0,
    }
    for name, rounds in runs.items():
        every = [t for run in rounds for t in run.times_ms]
        steady = [t for run in rounds for t in run.times_ms[args.warmup :]]
        errors = [e for run in rounds for e in run.errors_m]
        report[name] = {
            "frame_ms_median": statistics.median(every),
            "frame_ms_max": max(every),
            "frame_ms_max_per_round": [max(run.times_ms) for run in rounds],
            "cpu_ms_median": statistics.median(c for run in rounds for c in run.cpu_ms),
            "cpu_ms_max": max(c for run in rounds for c in run.cpu_ms),
            "steady_frame_ms_median": statistics.median(steady),
            "steady_frame_ms_max": max(steady),
            "leds_full_median": statistics.median(n for run in rounds for n in run.leds),
            "association_checks_median": statistics.median(c for run in rounds for c in run.checks),
            "association_checks_max": max(c for run in rounds for c in run.checks),
            "hypotheses_solved_max": max(c for run in rounds for c in run.solved),
            "frames_budget_exhausted": sum(run.truncated for run in rounds),
            "fixes": len(errors),
            "fix_error_cm_max": 100.0 * max(errors) if errors else None,
            "within_target": max(every) <= 20.0,
        }
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
