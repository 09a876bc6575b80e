"""``vlp-agent eval follow``: the fine layer of person following on rendered forward-camera sequences with
ground truth (``docs/following.md``, "eval follow").

A world (``examples/worlds/track_straight.toml``, ``track_left_turn.toml``, ...) runs on a stepped clock,
faster than real time. Its tagged user walks their path; the robot follows them 1 m behind, driven by the
agent's :class:`~agent.following.follower.Follower` on the user's TRUE position (an ideal laser track: this
evaluates the camera's tracking, not the following); the passers-by walk theirs. Each step the fake
Mercury reader (``drivers.fakes.rfid``, its channel model, read through the codec) reads the tags; every
read cycle the coarse layer (:class:`~agent.following.coarse.CoarseFilter` on the physical model's table)
predicts with the robot's motion and updates. Each forward-camera frame is rendered
(``drivers.sim.forward_render``) and the fine layer (:class:`~agent.following.fine.FineLayer`) runs as the
agent runs it: the coarse layer's window in the camera's view becomes a band of columns, the pre-locator
starts the tracker in the band and, while the target is hidden, feeds it re-acquisition hints from the
band; the mean-shift tracker detects occlusion from rho, coasts, and re-acquires.

Scored against the renderer's ground truth, the user's projected head-and-shoulders box:

* ``precision_20px``, ``success_auc``: OTB's, over every frame with the user in the image (frames before
  the tracker starts count as misses);
* ``identity_switches``: times the tracker, saying it tracks, is on someone other than the user for 3
  frames (0.2 s) or more in a row (who it is on: the person with at least a quarter of their body
  visible whose head box holds the tracker's centre, the nearest such centre); ``on_other_frames``
  counts every such frame, the one or two before an occlusion is flagged included;
* ``occlusions``: runs of frames where under 10 % of the user is visible (full occlusions), and
  ``reacquire_s``: per occlusion, from its last hidden frame to the first frame the tracker says
  tracking with its centre within 20 px of the truth; ``reacquire_s_max`` their largest (null when one
  never came back: a failure);
* ``fps``: frames per second of the fine layer's own time (pre-locator included), ``realtime_factor``:
  simulated seconds per wall second of the whole evaluation (rendering and the simulation included).

``--seed`` seeds the sensor noise, the RFID channel and the passers-by's timing (start +-0.15 s, speed
+-5 %); repeat it for several runs and their means.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np

from agent.commands.args import dumps_json
from agent.following.meanshift import Features

HIDDEN_SHARE = 0.1  # the user is fully occluded below this visible share
CANDIDATE_SHARE = 0.25  # a person the tracker can be "on" shows at least this much
STEP_S = 1.0 / 45.0


def add_parser(subparsers: Any) -> None:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "follow",
        help="track the followed user in rendered forward-camera frames; precision, identity, re-acquisition",
        description=textwrap.dedent(__doc__ or "").split("\n\n", 1)[0]
        + "\n\n"
        + textwrap.dedent(
            """\
            The robot follows the user 1 m behind on their true position (this measures the camera's
            tracking, not the following); RFID reads, the coarse layer, rendering and the fine layer run
            as the agent runs them. Reports precision_20px, success_auc, fps, identity_switches,
            occlusions (< 10 % of the user visible), reacquire_s_max (from the end of each full
            occlusion to the tracker back on the user within 20 px), realtime_factor."""
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--world", required=True, metavar="FILE", help="a world file with a tagged user and passers-by"
    )
    p.add_argument(
        "--seed",
        type=int,
        action="append",
        metavar="S",
        help="noise, RFID channel and passers-by timing (default 0); repeat for several runs and means",
    )
    p.add_argument(
        "--tracker",
        choices=[f.value for f in Features],
        default=Features.FULL.value,
        help="'full': colour and LBP texture (default); 'colour': colour-only mean shift",
    )
    p.add_argument(
        "--locator",
        choices=["omega", "hog", "upperbody"],
        default="omega",
        help="the pre-locator (agent.following.prelocate; default omega, the outline matcher)",
    )
    p.add_argument("--user", default="user", help="the followed person's name in the world (default user)")
    p.add_argument(
        "--seconds",
        type=float,
        help="simulated seconds (default: until the user's walk ends, plus 1 s)",
    )
    p.add_argument(
        "--param",
        metavar="NAME=VALUE",
        action="append",
        default=[],
        help="set one of the tracker's parameters (as eval track's --param; the fine layer's defaults are "
        "the omega silhouette and colour_space=hsv)",
    )
    p.add_argument(
        "--correct-every",
        type=int,
        default=3,
        metavar="N",
        help="frames between the pre-locator's corrections while tracking (FineLayerConfig.correct_every, "
        "default 3; 0: never, the mean shift alone between occlusions)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def _jittered(world: Any, user: str, seed: int) -> Any:
    rng = np.random.default_rng(seed + 7919)
    people = []
    for person in world.people:
        if person.name == user:
            people.append(person)
            continue
        people.append(
            dataclasses.replace(
                person,
                start_s=max(0.0, person.start_s + float(rng.uniform(-0.15, 0.15))),
                speed_mps=person.speed_mps * float(rng.uniform(0.95, 1.05)),
            )
        )
    return dataclasses.replace(world, people=tuple(people))


def _walk_s(person: Any) -> float:
    pts = np.asarray(person.path, dtype=np.float64)
    length = float(np.sum(np.hypot(*np.diff(pts, axis=0).T))) if len(pts) > 1 else 0.0
    return float(person.start_s) + length / max(float(person.speed_mps), 1e-3)


@dataclasses.dataclass
class _Frame:
    t_s: float
    state: str
    box: np.ndarray | None
    truth: np.ndarray | None  # the user's head box, None when out of the image
    visible: float
    identity: str | None  # who the tracker is on while tracking (None: nobody, or not tracking)


def run_sequence(
    world_path: str,
    seed: int,
    tracker: Features,
    locator_kind: str,
    user_name: str,
    seconds: float | None,
    params: list[str] | None = None,
    correct_every: int = 3,
) -> dict[str, Any]:
    import cv2

    from agent.following.coarse import (
        Antenna,
        CoarseFilter,
        RadioModel,
        default_table,
        observation_from_reads,
    )
    from agent.following.fine import FineLayer, FineLayerConfig, camera_band
    from agent.following.follower import Follower
    from agent.following.meanshift import Silhouette
    from agent.following.otb import centre_errors, overlaps, precision_at, success_auc
    from agent.following.person import PersonEstimate
    from agent.following.prelocate import HeadShoulderLocator, LocatorKind, PreLocatorConfig
    from drivers.errors import ConfigError
    from drivers.fakes.rfid import FakeRfidReader
    from drivers.samples import TagRead
    from drivers.sim.forward_render import ForwardRenderer, PersonState
    from drivers.sim.raycast import walls_array
    from drivers.sim.simulation import Simulation
    from drivers.sim.worldfile import load_world
    from firmware_protocol.rfid import (
        MercuryResponseDecoder,
        MercuryTagRead,
        decode_stream_message,
        encode_set_antenna_search_list,
        encode_start_continuous_read,
    )

    cv2.setNumThreads(1)
    world = load_world(world_path)
    user = next((p for p in world.people if p.name == user_name), None)
    if user is None:
        raise ConfigError("--user", f"{world_path} has no person named {user_name!r}")
    yaws = world.rfid.antenna_yaws_rad
    if not yaws:
        raise ConfigError(
            "--world", f"{world_path}: [rfid] antenna_yaws_deg is needed (a multi-antenna reader)"
        )
    world = _jittered(world, user_name, seed)
    duration = seconds if seconds is not None else min(_walk_s(user) + 1.0, 120.0)

    clock_t = [0.0]
    sim = Simulation(world, clock=lambda: clock_t[0], seed=seed)
    ports = tuple(range(1, len(yaws) + 1))
    fake = FakeRfidReader(sim, "mercury", seed=seed)
    decoder = MercuryResponseDecoder()
    fake.receive(encode_set_antenna_search_list([(q, q) for q in ports]), 0.0)
    decoder.feed(fake.receive(encode_start_continuous_read(), 0.0))
    table = default_table(RadioModel(tuple(Antenna(q, y) for q, y in zip(ports, yaws, strict=True))))
    coarse = CoarseFilter(table)
    cycle_s, next_cycle = 0.25, 0.25
    reads: list[TagRead] = []
    last_pose = sim.pose()

    model = world.forward_camera
    renderer = ForwardRenderer(model, walls_array(world.walls), seed=seed)
    half_fov = model.hfov_rad / 2.0
    kind = LocatorKind(locator_kind)
    locator = HeadShoulderLocator(PreLocatorConfig(kind=kind))
    from agent.commands.eval_track import tracker_config

    given = {item.partition("=")[0].strip() for item in params or []}
    defaults = [] if "colour_space" in given else ["colour_space=hsv"]
    fine = FineLayer(
        locator,
        FineLayerConfig(
            tracker=tracker_config(tracker, Silhouette.OMEGA, defaults + list(params or [])),
            correct_every=correct_every,
        ),
    )
    follower = Follower()
    frame_every = max(1, round(1.0 / (model.frame_rate_hz * STEP_S)))
    steps = math.ceil(duration / STEP_S)
    prev_xy: tuple[float, float] | None = None
    frames: list[_Frame] = []
    fine_s: list[float] = []
    prelocate_ms: list[float] = []
    wall0 = time.perf_counter()
    for k in range(1, steps + 1):
        t = k * STEP_S
        clock_t[0] = t
        pose = sim.pose()
        ux, uy, _, _ = sim.person_pose(user)
        velocity = (0.0, 0.0) if prev_xy is None else ((ux - prev_xy[0]) / STEP_S, (uy - prev_xy[1]) / STEP_S)
        prev_xy = (ux, uy)
        estimate = PersonEstimate((ux, uy), velocity, np.eye(4) * 0.01, 1, t, t)
        command = follower.step(t, (pose.x_m, pose.y_m, pose.yaw_rad), estimate, 0.0, None)
        sim.set_body_velocity(command.v_mps, command.omega_radps)
        for response in decoder.feed(fake.poll(t)):
            message = decode_stream_message(response)
            if isinstance(message, MercuryTagRead):
                reads.append(
                    TagRead(
                        message.epc_hex, round(t * 1e9), "sim", float(message.rssi_dbm), message.rx_antenna
                    )
                )
        if t + 1e-9 >= next_cycle:
            dx, dy = pose.x_m - last_pose.x_m, pose.y_m - last_pose.y_m
            c, s = math.cos(last_pose.yaw_rad), math.sin(last_pose.yaw_rad)
            turn = math.remainder(pose.yaw_rad - last_pose.yaw_rad, math.tau)
            coarse.predict(cycle_s, c * dx + s * dy, -s * dx + c * dy, turn)
            coarse.update(observation_from_reads(reads, ports, user.tag_id))
            reads, last_pose, next_cycle = [], pose, next_cycle + cycle_s
        if k % frame_every:
            continue
        people = [PersonState(p, *sim.person_pose(p, t)) for p in world.people]
        image, truth = renderer.render(pose, people, t)
        window = coarse.within(0.0, half_fov)
        band = camera_band(
            window.probability,
            window.bearing_rad,
            model.focal_length_px,
            model.principal_point_px[0],
            model.width_px,
        )
        t0 = time.perf_counter()
        result = fine.update(image, band)
        fine_s.append(time.perf_counter() - t0)
        if result.prelocated:
            prelocate_ms.append(locator.last_ms)
        view = truth.person(user_name)
        truth_box = None
        if view is not None and view.head_box is not None:
            hb = view.head_box
            truth_box = np.array([hb.x, hb.y, hb.w, hb.h], dtype=np.float64)
        identity = None
        if result.state == "tracking" and result.box is not None:
            identity = _identity(result.box, truth.people)
        frames.append(
            _Frame(
                t,
                str(result.state),
                None if result.box is None else np.asarray(result.box, dtype=np.float64),
                truth_box,
                0.0 if view is None else float(view.visible),
                identity,
            )
        )
    wall_s = time.perf_counter() - wall0
    scored = [f for f in frames if f.truth is not None]
    truth_boxes = np.array([f.truth for f in scored]) if scored else np.zeros((0, 4))
    far = np.array([-1e4, -1e4, 1.0, 1.0])
    pred = np.array([f.box if f.box is not None else far for f in scored]) if scored else np.zeros((0, 4))
    errors = centre_errors(pred, truth_boxes) if scored else np.zeros(0)
    ious = overlaps(pred, truth_boxes) if scored else np.zeros(0)
    reacquire = _reacquire(frames)
    switches = _switches([f.identity for f in frames], user_name)
    fine_ms = np.array(fine_s) * 1e3
    return {
        "world": world.name,
        "seed": seed,
        "tracker": tracker.value,
        "locator": kind.value,
        "seconds": duration,
        "frames": len(frames),
        "scored_frames": len(scored),
        "precision_20px": precision_at(errors, 20.0) if len(errors) else None,
        "success_auc": success_auc(ious) if len(ious) else None,
        "mean_centre_error_px": float(np.mean(np.minimum(errors, 1e3))) if len(errors) else None,
        "identity_switches": switches,
        "on_other_frames": sum(1 for f in frames if f.identity not in (None, user_name)),
        "occlusions": len(reacquire),
        "hidden_frames": sum(1 for f in frames if f.truth is not None and f.visible < HIDDEN_SHARE),
        "reacquire_s": reacquire,
        "reacquire_s_max": None
        if any(r is None for r in reacquire)
        else max((r for r in reacquire if r is not None), default=0.0),
        "first_tracking_s": next((f.t_s for f in frames if f.state == "tracking"), None),
        "state_frames": {
            s: sum(1 for f in frames if f.state == s) for s in ("searching", "tracking", "occluded", "lost")
        },
        "fps": len(fine_s) / float(np.sum(fine_s)) if fine_s else None,
        "fine_ms_median": float(np.median(fine_ms)) if len(fine_ms) else None,
        "fine_ms_p95": float(np.percentile(fine_ms, 95)) if len(fine_ms) else None,
        "prelocate_ms_median": float(np.median(prelocate_ms)) if prelocate_ms else None,
        "realtime_factor": duration / wall_s if wall_s > 0 else None,
    }


SWITCH_FRAMES = 3  # frames on another person that make an identity switch


def _switches(identities: list[str | None], user: str) -> int:
    """Runs of at least SWITCH_FRAMES consecutive frames tracking someone other than the user (a frame not
    tracking, or on nobody, ends a run): a box that slides onto an occluder for a frame or two before the
    occlusion is flagged is not counted here but in ``on_other_frames``."""
    count, run, last = 0, 0, None
    for who in identities:
        run = (run + 1 if who == last else 1) if who is not None and who != user else 0
        last = who
        if run == SWITCH_FRAMES:
            count += 1
    return count


def _identity(box: np.ndarray, people: Any) -> str | None:
    cx, cy = float(box[0] + box[2] / 2.0), float(box[1] + box[3] / 2.0)
    best: tuple[float, str] | None = None
    for p in people:
        hb = p.head_box
        if hb is None or p.visible < CANDIDATE_SHARE:
            continue
        if not (hb.x <= cx < hb.x + hb.w and hb.y <= cy < hb.y + hb.h):
            continue
        d = math.hypot(cx - (hb.x + hb.w / 2.0), cy - (hb.y + hb.h / 2.0)) / math.hypot(hb.w, hb.h)
        if best is None or d < best[0]:
            best = (d, p.name)
    return None if best is None else best[1]


def _reacquire(frames: list[_Frame]) -> list[float | None]:
    """Per full occlusion (a run of frames with the user in the image but under HIDDEN_SHARE visible): the
    seconds from its last hidden frame to the first frame tracking within 20 px; None: never."""
    out: list[float | None] = []
    i = 0
    n = len(frames)
    while i < n:
        f = frames[i]
        if f.truth is None or f.visible >= HIDDEN_SHARE:
            i += 1
            continue
        j = i
        while j + 1 < n and frames[j + 1].truth is not None and frames[j + 1].visible < HIDDEN_SHARE:
            j += 1
        end_t = frames[j].t_s
        back: float | None = None
        for g in frames[j + 1 :]:
            if g.state == "tracking" and g.box is not None and g.truth is not None:
                err = math.hypot(
                    g.box[0] + g.box[2] / 2.0 - g.truth[0] - g.truth[2] / 2.0,
                    g.box[1] + g.box[3] / 2.0 - g.truth[1] - g.truth[3] / 2.0,
                )
                if err <= 20.0:
                    back = g.t_s - end_t
                    break
        out.append(back)
        i = j + 1
    return out


_MEAN_KEYS = ("precision_20px", "success_auc", "fps", "fine_ms_median", "realtime_factor")


def run(args: argparse.Namespace) -> int:
    from drivers.errors import ConfigError

    if not Path(args.world).is_file():
        raise ConfigError("--world", f"{args.world}: no such file")
    if args.correct_every < 0:
        raise ConfigError("--correct-every", "must be 0 or more")
    if args.seconds is not None and args.seconds <= 0:
        raise ConfigError("--seconds", "must be positive")
    seeds = args.seed or [0]
    runs = []
    for seed in seeds:
        runs.append(
            run_sequence(
                args.world,
                seed,
                Features(args.tracker),
                args.locator,
                args.user,
                args.seconds,
                args.param,
                args.correct_every,
            )
        )
        if not args.json and len(seeds) > 1:
            print(f"  seed {seed} done", file=sys.stderr, flush=True)
    if len(runs) == 1:
        summary = runs[0]
    else:
        summary = {"world": runs[0]["world"], "tracker": args.tracker, "seeds": seeds, "runs": runs}
        for key in _MEAN_KEYS:
            values = [r[key] for r in runs if r[key] is not None]
            summary[key] = float(np.mean(values)) if values else None
        summary["precision_20px_min"] = min((r["precision_20px"] or 0.0) for r in runs)
        summary["identity_switches"] = int(sum(r["identity_switches"] for r in runs))
        maxima = [r["reacquire_s_max"] for r in runs]
        summary["reacquire_s_max"] = None if any(m is None for m in maxima) else max(maxima)
        summary["occlusions"] = int(sum(r["occlusions"] for r in runs))
    if args.json:
        print(dumps_json(summary, sort_keys=True))
        return 0
    print(f"world {runs[0]['world']}, tracker {args.tracker}, locator {args.locator}")
    heads = ("seed", "frames", "prec@20", "AUC", "switches", "occl.", "reacq s", "fps", "x real")
    print(" ".join(f"{h:>8}" for h in heads))
    for r in runs:
        reacq = "never" if r["reacquire_s_max"] is None else f"{r['reacquire_s_max']:.2f}"
        cells = (
            str(r["seed"]),
            str(r["scored_frames"]),
            f"{r['precision_20px'] or 0.0:.3f}",
            f"{r['success_auc'] or 0.0:.3f}",
            str(r["identity_switches"]),
            str(r["occlusions"]),
            reacq,
            f"{r['fps'] or 0.0:.0f}",
            f"{r['realtime_factor'] or 0.0:.1f}",
        )
        print(" ".join(f"{c:>8}" for c in cells))
    return 0
