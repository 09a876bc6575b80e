"""The person tracker's cost per 640 x 480 frame while tracking, and the head-shoulder pre-locator's cost
when it runs, on one core. Prints one JSON object.

    python benchmarks/tracker_speed.py [--frames 120] [--repeats 5] [--scale-search contrast|ladder]
        [--translation none|place|refine]

Budgets (issue 23): the fine layer <= 5 ms median per 640 x 480 frame while tracking; the pre-locator
<= 30 ms. The frames are the synthetic scene (``agent.following.synthetic``, no passer-by) at 640 x 480 with
the target at two sizes a forward camera sees a person behind whom the robot follows: a whole body
(120 x 300 px, ellipse kernel) and head and shoulders (160 x 160 px, Omega silhouette). Beside them, in the
same run and on the same frames, one plain pass over the frame (``numpy.sum`` of every byte) is timed, so a
slow or busy machine shows as a ratio that stays put (``*_over_plain_pass``).

The pre-locator runs on a real frame when ``../shared/data/person`` is there (OTB Couple frame 1, two
people, scaled to 640 x 480), else on a synthetic frame: over the whole frame shrunk to 320 and to 160 px
wide (a user close ahead is large), and over a band of a third of the width (the coarse layer's sector)
at full resolution; and the scale anchor's search around a tracked walker (``hog_around_track``: OTB
Woman's first box, the image scaled so that it is 130 px tall).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agent.following.meanshift import (
    Features,
    MeanShiftTracker,
    ScaleSearch,
    Silhouette,
    TextureWeighting,
    TrackerConfig,
    Translation,
)
from agent.following.prelocate import HeadShoulderLocator, LocatorKind, PreLocatorConfig
from agent.following.synthetic import CrossingScene, crossing_sequence

SHARED = Path(os.environ.get("VLP_SHARED", Path(__file__).resolve().parents[2] / "shared"))


def _ms(samples: list[float]) -> dict[str, float]:
    ordered = sorted(samples)
    return {
        "median_ms": round(statistics.median(ordered), 3),
        "p95_ms": round(ordered[int(0.95 * (len(ordered) - 1))], 3),
    }


def tracker_case(
    size: tuple[int, int],
    silhouette: Silhouette,
    frames: int,
    scale: ScaleSearch,
    translation: Translation,
    texture: TextureWeighting = TextureWeighting.SELECT,
) -> dict[str, object]:
    scene = CrossingScene(
        width_px=640,
        height_px=480,
        frames=frames,
        target_size_px=size,
        target_start_px=(200.0, 240.0),
        passer=False,  # every frame a tracking frame; the passer-by's cost is the p95's business
        seed=0,
    )
    sequence = list(crossing_sequence(scene))
    plain = []
    for image, _ in sequence:
        t0 = time.perf_counter()
        np.sum(image, dtype=np.uint64)
        plain.append((time.perf_counter() - t0) * 1e3)
    out: dict[str, object] = {"target_px": list(size), "silhouette": silhouette.value}
    plain_ms = statistics.median(plain)
    out["plain_pass_ms_median"] = round(plain_ms, 3)
    for features in Features:
        tracker = MeanShiftTracker(
            TrackerConfig(
                features=features,
                silhouette=silhouette,
                scale_search=scale,
                translation=translation,
                texture_weighting=texture,
            )
        )
        tracker.start(sequence[0][0], sequence[0][1])
        times = []
        tracking = 0
        for image, _ in sequence[1:]:
            t0 = time.perf_counter()
            result = tracker.update(image)
            elapsed = (time.perf_counter() - t0) * 1e3
            if result.state.value == "tracking":  # the budget is "while tracking"
                times.append(elapsed)
                tracking += 1
        stats = _ms(times)
        out[features.value] = {
            **stats,
            "tracking_frames": tracking,
            "median_over_plain_pass": round(stats["median_ms"] / plain_ms, 1),
        }
    return out


def prelocator_frame() -> tuple[np.ndarray, str]:
    path = SHARED / "data/person/Couple/img/0001.jpg"
    image = cv2.imread(str(path)) if path.is_file() else None
    if image is not None:
        return cv2.resize(image, (640, 480), interpolation=cv2.INTER_LINEAR), "OTB Couple frame 1 at 640x480"
    frame, _ = next(iter(crossing_sequence(CrossingScene(width_px=640, height_px=480))))
    return frame, "synthetic crossing scene (../shared absent)"


def prelocator_case(repeats: int) -> dict[str, object]:
    frame, source = prelocator_frame()
    out: dict[str, object] = {"frame": source}
    for kind in LocatorKind:
        for name, band, width in (
            ("whole_frame_at_320px", None, 320),
            ("whole_frame_at_160px", None, 160),
            ("band_third_full_res", (213, 427), 640),
        ):
            locator = HeadShoulderLocator(
                PreLocatorConfig(kind=kind, max_width_px=width, omega_width_px=min(width, 160) // 2 * 2)
                if kind is not LocatorKind.OMEGA
                else PreLocatorConfig(kind=kind, omega_width_px=width // 2)
            )
            locator.locate(frame, band)  # warm-up
            times = []
            found = 0
            for _ in range(repeats):
                found = len(locator.locate(frame, band))
                times.append(locator.last_ms)
            out[f"{kind.value}_{name}"] = {**_ms(times), "detections": found}
    out["hog_around_track"] = anchor_case(repeats)
    return out


def anchor_case(repeats: int) -> dict[str, object]:
    """The scale anchor's search (``agent.following.anchor``): HOG in the window around a walker's box,
    scaled so the start box is 130 px tall. Its cost follows the box's aspect, not the frame's size."""
    from agent.following.anchor import ScaleAnchor, ScaleAnchorConfig

    folder = SHARED / "data/person/Woman"
    if (folder / "img/0001.jpg").is_file():
        from agent.following.otb import load_sequence

        target = load_sequence(folder).targets[0]
        frame = cv2.imread(str(folder / "img/0001.jpg"))
        box, source = target.boxes[0], "OTB Woman frame 1, its first box (21 x 95 px)"
    else:
        frame, box = next(iter(crossing_sequence(CrossingScene(width_px=640, height_px=480))))
        source = "synthetic crossing scene (../shared absent)"
    config = ScaleAnchorConfig(every=5)
    locator = HeadShoulderLocator(PreLocatorConfig(scale_step=config.detector_scale_step))
    scale = ScaleAnchor.upscale_for(config, np.asarray(box, dtype=np.float64))
    locator.locate_around(frame, box, scale)  # warm-up
    times = []
    found = 0
    for _ in range(repeats):
        found = len(locator.locate_around(frame, box, scale, config.window_width, config.window_height))
        times.append(locator.last_ms)
    return {"frame": source, **_ms(times), "detections": found}


def rendered_frames(frames: int) -> list[np.ndarray]:
    """Forward-camera frames of ``examples/worlds/track_straight.toml`` from 1 m behind the walking user (no
    passer-by in view): what the fine layer sees while following."""
    from drivers.sim.forward_render import ForwardRenderer, PersonState
    from drivers.sim.raycast import walls_array
    from drivers.sim.simulation import Simulation
    from drivers.sim.world import Pose2D
    from drivers.sim.worldfile import load_world

    world = load_world(Path(__file__).resolve().parents[1] / "examples/worlds/track_straight.toml")
    clock = [0.0]
    sim = Simulation(world, clock=lambda: clock[0], seed=0)
    renderer = ForwardRenderer(world.forward_camera, walls_array(world.walls), seed=0)
    user = world.people[0]
    out = []
    for k in range(frames):
        clock[0] = 2.5 + k / 15.0  # the user walking, the passers-by not yet in view
        x, y, _, _ = sim.person_pose(user)
        people = [PersonState(user, *sim.person_pose(user))]
        image, _ = renderer.render(Pose2D(x - 1.0, y, 0.0), people, clock[0])
        out.append(image.copy())
    return out


def fine_layer_case(
    frames: int,
    scale: ScaleSearch,
    translation: Translation,
    texture: TextureWeighting = TextureWeighting.SELECT,
) -> dict[str, object]:
    """The fine layer as ``eval follow`` runs it (HSV colour, Omega silhouette, the omega pre-locator
    correcting the box every 3 frames) on rendered frames: per frame, the tracker alone and the whole layer
    (pre-locator frames included), with this thread's CPU time beside the wall time."""
    from agent.following.fine import FineLayer, FineLayerConfig
    from agent.following.meanshift import ColourSpace

    images = rendered_frames(frames)
    plain = []
    for image in images:
        t0 = time.perf_counter()
        np.sum(image, dtype=np.uint64)
        plain.append((time.perf_counter() - t0) * 1e3)
    plain_ms = statistics.median(plain)
    out: dict[str, object] = {
        "frames": "track_straight rendered, 1 m behind the user",
        "plain_pass_ms_median": round(plain_ms, 3),
    }
    for features in Features:
        config = FineLayerConfig(
            tracker=TrackerConfig(
                features=features,
                silhouette=Silhouette.OMEGA,
                colour_space=ColourSpace.HSV,
                scale_search=scale,
                translation=translation,
                texture_weighting=texture,
            )
        )
        layer = FineLayer(HeadShoulderLocator(PreLocatorConfig(kind=LocatorKind.OMEGA)), config)
        layer.update(images[0])
        wall, cpu, tracker_only = [], [], []
        for image in images[1:]:
            t0, c0 = time.perf_counter(), time.thread_time()
            result = layer.update(image)
            wall.append((time.perf_counter() - t0) * 1e3)
            cpu.append((time.thread_time() - c0) * 1e3)
            if not result.prelocated and result.state.value == "tracking":
                tracker_only.append(wall[-1])
        stats = _ms(wall)
        out[features.value] = {
            **stats,
            "mean_ms": round(statistics.fmean(wall), 3),
            "cpu_median_ms": round(statistics.median(cpu), 3),
            "cpu_mean_ms": round(statistics.fmean(cpu), 3),
            "tracker_only_median_ms": round(statistics.median(tracker_only), 3) if tracker_only else None,
            "median_over_plain_pass": round(stats["median_ms"] / plain_ms, 1),
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=120, help="frames per tracker case (default 120)")
    parser.add_argument("--repeats", type=int, default=5, help="pre-locator calls per case (default 5)")
    parser.add_argument(
        "--scale-search",
        choices=[s.value for s in ScaleSearch],
        default=TrackerConfig().scale_search.value,
        help="the trackers' scale_search (default: TrackerConfig's)",
    )
    parser.add_argument(
        "--translation",
        choices=[t.value for t in Translation],
        default=TrackerConfig().translation.value,
        help="the trackers' translation (DSST's translation filter; place needs --scale-search ladder)",
    )
    parser.add_argument(
        "--texture-weighting",
        choices=[t.value for t in TextureWeighting],
        default=TrackerConfig().texture_weighting.value,
        help="the full tracker's texture_weighting (select: feature selection; default: TrackerConfig's)",
    )
    args = parser.parse_args()
    texture = TextureWeighting(args.texture_weighting)
    scale = ScaleSearch(args.scale_search)
    translation = Translation(args.translation)
    cv2.setNumThreads(1)
    result: dict[str, object] = {
        "frame_px": [640, 480],
        "budget_ms": {"tracker_median": 5.0, "prelocator": 30.0},
        "scale_search": scale.value,
        "translation": translation.value,
        "texture_weighting": texture.value,
        "tracker_body": tracker_case(
            (120, 300), Silhouette.ELLIPSE, args.frames, scale, translation, texture
        ),
        "tracker_head_shoulder": tracker_case(
            (160, 160), Silhouette.OMEGA, args.frames, scale, translation, texture
        ),
        "fine_layer_rendered": fine_layer_case(args.frames, scale, translation, texture),
        "prelocator": prelocator_case(args.repeats),
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
