"""Speed of the forward camera's renderer (``drivers/sim/forward_render.py``) on the person-following worlds.

Renders the frames the simulated forward camera would make of a following scenario (the robot standing
at its start, the user and the passers-by walking) and prints one JSON object: per frame the median, p90
and max wall time and the median CPU time (this thread's) in ms, with the floor measured in the same run:
the cost of copying one 640x480 BGR frame (``floor_copy_ms``), and ``ratio_to_copy`` = median / floor,
which a loaded machine inflates less than the raw times. Also how many frames show the user partly or
(nearly) fully hidden (under 10 % of their body's pixels visible) as the passers-by cross, from the
renderer's ground truth. The aim is <= 10 ms median per
640x480 frame on one core.

    python benchmarks/forward_render.py
    python benchmarks/forward_render.py --world examples/worlds/follow_left_turn.toml --seconds 30
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.camera.sim_forward import people_states
from drivers.sim.forward_render import ForwardRenderer
from drivers.sim.raycast import walls_array
from drivers.sim.simulation import Simulation
from drivers.sim.worldfile import load_world

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--world", default=str(REPO / "examples" / "worlds" / "follow_straight.toml"))
    p.add_argument("--seconds", type=float, default=20.0, help="simulated seconds of frames (default 20)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    cv2.setNumThreads(1)
    world = load_world(args.world)
    model = world.forward_camera
    clock = [0.0]
    sim = Simulation(world, clock=lambda: clock[0], seed=args.seed)
    renderer = ForwardRenderer(model, walls_array(world.walls), seed=args.seed)
    out = np.empty((model.height_px, model.width_px, 3), dtype=np.uint8)
    src = np.empty_like(out)
    wall_ms, cpu_ms, floor_ms = [], [], []
    hidden = partly = 0
    frames = int(args.seconds * model.frame_rate_hz)
    user = world.people[0].name if world.people else None
    for k in range(frames):
        clock[0] = k / model.frame_rate_hz
        base = sim.pose_at(clock[0])
        states = people_states(sim, clock[0])
        c0, w0 = time.thread_time(), time.perf_counter()
        _, truth = renderer.render(base, states, clock[0], out)
        w1, c1 = time.perf_counter(), time.thread_time()
        np.copyto(src, out)
        w2 = time.perf_counter()
        np.copyto(out, src)
        floor_ms.append((time.perf_counter() - w2) * 1e3)
        wall_ms.append((w1 - w0) * 1e3)
        cpu_ms.append((c1 - c0) * 1e3)
        seen = truth.person(user) if user else None
        if seen is not None and seen.box is not None:
            hidden += seen.visible < 0.1
            partly += 0.1 <= seen.visible < 0.9
    median = float(np.median(wall_ms))
    floor = float(np.median(floor_ms))
    print(
        json.dumps(
            {
                "world": world.name,
                "size": [model.width_px, model.height_px],
                "frames": frames,
                "render_ms_median": round(median, 3),
                "render_ms_p90": round(float(np.percentile(wall_ms, 90)), 3),
                "render_ms_max": round(float(np.max(wall_ms)), 3),
                "cpu_render_ms_median": round(float(np.median(cpu_ms)), 3),
                "floor_copy_ms": round(floor, 4),
                "ratio_to_copy": round(median / floor, 1) if floor > 0 else None,
                "user_frames_partly_hidden": int(partly),
                "user_frames_hidden": int(hidden),
            }
        )
    )


if __name__ == "__main__":
    main()
