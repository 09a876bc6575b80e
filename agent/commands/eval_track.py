"""``vlp-agent eval track``: the person tracker (the fine layer of following) on OTB-style image sequences.

Each target is tracked from its first ground-truth box only (no later box is looked at until scoring) and
scored the way OTB scores a one-pass evaluation: precision at 20 px and success AUC
(``agent.following.otb``). ``fps`` counts the tracker's own time per frame, not the JPEG decoding
(``fps_with_decode`` does).
"""

from __future__ import annotations

import argparse
import dataclasses
import enum
import sys
import textwrap
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from agent.commands.args import dumps_json
from agent.following.anchor import ScaleAnchorConfig
from agent.following.meanshift import Features, Silhouette, TrackerConfig

if TYPE_CHECKING:  # imported where it is used: it loads OpenCV's detectors
    from agent.following.prelocate import HeadShoulderLocator, ImageU8

ANCHOR_PREFIX = "anchor_"

FloatArray = np.ndarray[Any, np.dtype[np.float64]]


def add_parser(subparsers: Any) -> None:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "track",
        help="run the person tracker on OTB-style image sequences; report OTB precision and success",
        description=textwrap.dedent(
            """\
            Run the person tracker (multi-feature mean shift: colour and LBP texture under a silhouette
            kernel, docs/following.md) on OTB-style folders: img/*.jpg and groundtruth_rect*.txt (one
            x,y,w,h box per line, 1-based, comma/TAB/space separated; a sequence with several targets
            has groundtruth_rect.1.txt, .2.txt, ... and each is tracked on its own). The tracker starts
            from the first ground-truth box only.

            Reports per target: precision_20px (fraction of frames whose box centre is within 20 px of
            the ground truth's), success_auc (area under OTB's success plot, IoU thresholds 0..1 step
            0.05), fps (tracker time only), fps_with_decode, frames, occluded_frames (frames the tracker
            coasted, believing the target hidden), mean_centre_error_px; per sequence the mean over its
            targets; with several sequences, the mean over sequences (sequence-weighted) and over
            targets."""
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--sequence",
        metavar="DIR",
        action="append",
        required=True,
        help="an OTB-style folder (img/*.jpg + groundtruth_rect*.txt); repeat for several",
    )
    p.add_argument(
        "--tracker",
        choices=[f.value for f in Features],
        default=Features.FULL.value,
        help="'full': colour and texture, rho = rho_colour^a * rho_texture^b (default; a = b = 1 is the "
        "seed paper's product, --param adaptive_weights=false); 'colour': colour-only mean shift, the same "
        "code without the texture",
    )
    p.add_argument(
        "--silhouette",
        choices=[s.value for s in Silhouette],
        default=Silhouette.ELLIPSE.value,
        help="kernel mask inside the box (default: ellipse; 'omega' is for head-shoulder boxes)",
    )
    p.add_argument(
        "--frames", type=int, metavar="N", help="score only the first N frames of each target (quick runs)"
    )
    p.add_argument(
        "--param",
        metavar="NAME=VALUE",
        action="append",
        default=[],
        help="set one of the tracker's parameters (agent.following.meanshift.TrackerConfig, listed in "
        "docs/following.md), e.g. --param scale_gain=0 --param adaptive_weights=false; repeat for several. "
        "Names starting anchor_ set the pre-locator's scale anchor "
        "(agent.following.anchor.ScaleAnchorConfig, off by default): --param anchor_every=5 runs the HOG "
        "people detector around the track every 5 tracked frames (and on re-acquisition) and pulls the "
        "box's size toward a matching detection's",
    )
    p.add_argument(
        "--sre",
        action="store_true",
        help="also OTB's spatial robustness evaluation: each target tracked 12 more times from its first "
        "box shifted by 10 %% of its size in 8 directions and scaled by 0.8, 0.9, 1.1, 1.2; "
        "sre_precision_20px and sre_success_auc are the means over those runs (13 times the time)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def sre_boxes(box: FloatArray) -> list[FloatArray]:
    """OTB's spatial robustness starts (Wu, Lim, Yang 2013): the box shifted by 10 % of its width and
    height in the 8 directions, and scaled about its centre by 0.8, 0.9, 1.1 and 1.2."""
    x, y, w, h = (float(v) for v in box)
    out = []
    for dx, dy in ((-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)):
        out.append(np.array([x + 0.1 * dx * w, y + 0.1 * dy * h, w, h]))
    for s in (0.8, 0.9, 1.1, 1.2):
        out.append(np.array([x + w * (1 - s) / 2, y + h * (1 - s) / 2, w * s, h * s]))
    return out


def tracker_config(features: Features, silhouette: Silhouette, params: list[str]) -> TrackerConfig:
    """The tracker's configuration with ``NAME=VALUE`` overrides, each VALUE read as its field's type."""
    from drivers.errors import ConfigError

    values: dict[str, Any] = {"features": features, "silhouette": silhouette}
    values.update(_parse_fields(TrackerConfig, params, "", ("features", "silhouette")))
    try:
        return TrackerConfig(**values)
    except ValueError as exc:
        raise ConfigError("--param", str(exc)) from None


def anchor_config(params: list[str]) -> ScaleAnchorConfig:
    """The detector anchor's configuration from ``anchor_NAME=VALUE`` items (``anchor_every=5`` sets
    ``ScaleAnchorConfig.every``)."""
    from drivers.errors import ConfigError

    try:
        return ScaleAnchorConfig(**_parse_fields(ScaleAnchorConfig, params, ANCHOR_PREFIX, ()))
    except ValueError as exc:
        raise ConfigError("--param", str(exc)) from None


def split_params(params: list[str]) -> tuple[list[str], list[str]]:
    """``--param`` items for the tracker, and those for the detector anchor (named ``anchor_...``)."""
    anchor = [p for p in params if p.strip().startswith(ANCHOR_PREFIX)]
    return [p for p in params if p not in anchor], anchor


def _parse_fields(cls: Any, params: list[str], prefix: str, fixed: tuple[str, ...]) -> dict[str, Any]:
    from drivers.errors import ConfigError

    fields = {f.name: f for f in dataclasses.fields(cls)}
    defaults = cls()
    values: dict[str, Any] = {}
    for item in params:
        full, sep, text = item.partition("=")
        full = full.strip()
        name = full[len(prefix) :] if full.startswith(prefix) else ""
        if not sep or name not in fields or name in fixed:
            known = ", ".join(prefix + n for n in fields if n not in fixed)
            raise ConfigError("--param", f"{item!r}: want NAME=VALUE with NAME one of {known}")
        default = getattr(defaults, name)
        try:
            if isinstance(default, bool):
                if text.strip().lower() not in ("true", "false", "1", "0"):
                    raise ValueError(text)
                values[name] = text.strip().lower() in ("true", "1")
            elif isinstance(default, enum.Enum):
                values[name] = type(default)(text.strip())
            elif isinstance(default, str):
                values[name] = text.strip()
            else:
                values[name] = type(default)(text)
        except ValueError:
            raise ConfigError("--param", f"{item!r}: not a {type(default).__name__}") from None
    return values


def track_target(
    frames: list[Path], start: FloatArray, config: TrackerConfig, anchor: ScaleAnchorConfig | None = None
) -> tuple[FloatArray, dict[str, float]]:
    """Track one target from ``start`` (its first box) over ``frames``; its boxes (N, 4) and timing.

    With ``anchor`` (``every`` > 0) the fine layer's pre-locator anchors the size: it runs around the
    start box on the first frame (the anchor learns its ratios there, from the start box only), then
    around the track every ``every`` tracked frames and on the first tracked frame after a
    re-acquisition (``agent.following.anchor``)."""
    import cv2

    from agent.following.anchor import ScaleAnchor
    from agent.following.meanshift import MeanShiftTracker, TrackState

    tracker = MeanShiftTracker(config)
    anchored = anchor is not None and anchor.every > 0
    scale_anchor = ScaleAnchor(anchor) if anchor is not None and anchored else None
    locator = _anchor_locator(anchor) if anchor is not None and anchored else None
    out = np.zeros((len(frames), 4))
    track_s = 0.0
    locate_s: list[float] = []
    occluded = 0
    since = 0
    was_tracking = True
    t_start = time.perf_counter()
    for i, path in enumerate(frames):
        decoded = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if decoded is None:
            from drivers.errors import ConfigError

            raise ConfigError("--sequence", f"{path} is not a readable image")
        image = np.asarray(decoded, dtype=np.uint8)
        t0 = time.perf_counter()
        if i == 0:
            tracker.start(image, start)
            out[0] = start
            if scale_anchor is not None and locator is not None and anchor is not None:
                found = _around(locator, image, start, anchor, ScaleAnchor.upscale_for(anchor, start))
                locate_s.append(locator.last_ms)
                scale_anchor.start(start, found)
        else:
            result = tracker.update(image)
            tracking = result.state is TrackState.TRACKING
            occluded += not tracking
            box = result.box
            if scale_anchor is not None and locator is not None and anchor is not None and tracking:
                scale_anchor.predict()
                since += 1
                if scale_anchor.learnt and (since >= anchor.every or not was_tracking):
                    since = 0
                    found = _around(locator, image, box, anchor, scale_anchor.upscale)
                    locate_s.append(locator.last_ms)
                    pull = scale_anchor.observe(box, found)
                    if pull is not None:
                        tracker.rescale(pull.factor, pull.centre)
                        box = tracker.box
            was_tracking = tracking
            out[i] = box
        track_s += time.perf_counter() - t0
    wall_s = time.perf_counter() - t_start
    n = len(frames)
    timing: dict[str, float] = {
        "fps": n / track_s if track_s > 0 else float("inf"),
        "fps_with_decode": n / wall_s if wall_s > 0 else float("inf"),
        "occluded_frames": occluded,
    }
    if scale_anchor is not None:
        timing["anchor_learnt"] = float(scale_anchor.learnt)
        timing["anchor_measurements"] = scale_anchor.measurements
        timing["anchor_runs"] = len(locate_s)
        timing["anchor_locate_ms_median"] = float(np.median(locate_s)) if locate_s else 0.0
    return out, timing


def _anchor_locator(anchor: ScaleAnchorConfig) -> HeadShoulderLocator:
    from agent.following.prelocate import HeadShoulderLocator, LocatorKind, PreLocatorConfig

    return HeadShoulderLocator(
        PreLocatorConfig(kind=LocatorKind(anchor.detector), scale_step=anchor.detector_scale_step)
    )


def _around(
    locator: HeadShoulderLocator, image: ImageU8, box: FloatArray, anchor: ScaleAnchorConfig, scale: float
) -> list[FloatArray]:
    found = locator.locate_around(image, box, scale, anchor.window_width, anchor.window_height)
    return [d.box for d in found]


def evaluate_sequence(
    directory: str,
    config: TrackerConfig,
    max_frames: int | None = None,
    sre: bool = False,
    anchor: ScaleAnchorConfig | None = None,
) -> dict[str, Any]:
    from agent.following.otb import centre_errors, load_sequence, overlaps, precision_at, success_auc

    sequence = load_sequence(directory)
    targets = []
    for target in sequence.targets:
        n = len(target.boxes) if max_frames is None else min(max_frames, len(target.boxes))
        truth = target.boxes[:n]
        frames = list(sequence.frames[:n])
        boxes, timing = track_target(frames, truth[0], config, anchor)
        errors = centre_errors(boxes, truth)
        ious = overlaps(boxes, truth)
        row: dict[str, Any] = {
            "target": target.name,
            "groundtruth": target.groundtruth_file.name,
            "frames": n,
            "precision_20px": precision_at(errors, 20.0),
            "success_auc": success_auc(ious),
            "mean_centre_error_px": float(np.mean(errors)),
            **timing,
        }
        if sre:
            runs = [track_target(frames, start, config, anchor)[0] for start in sre_boxes(truth[0])]
            row["sre_precision_20px"] = float(np.mean([precision_at(centre_errors(b, truth)) for b in runs]))
            row["sre_success_auc"] = float(np.mean([success_auc(overlaps(b, truth)) for b in runs]))
        targets.append(row)
    return {
        "sequence": sequence.name,
        "path": str(directory),
        "targets": targets,
        **_means(targets),
    }


def _named(params: list[str]) -> set[str]:
    return {item.partition("=")[0].strip() for item in params}


def _means(rows: list[dict[str, Any]]) -> dict[str, Any]:
    keys = ["precision_20px", "success_auc", "fps", "fps_with_decode", "mean_centre_error_px"]
    keys += [k for k in ("sre_precision_20px", "sre_success_auc") if all(k in r for r in rows)]
    out: dict[str, Any] = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    out["frames"] = int(sum(r["frames"] for r in rows))
    return out


def run(args: argparse.Namespace) -> int:
    from drivers.errors import ConfigError

    if args.frames is not None and args.frames < 2:
        raise ConfigError("--frames", "must be at least 2")
    features = Features(args.tracker)
    silhouette = Silhouette(args.silhouette)
    tracker_params, anchor_params = split_params(args.param)
    config = tracker_config(features, silhouette, tracker_params)
    anchor = anchor_config(anchor_params)
    sequences = []
    for directory in args.sequence:
        sequences.append(evaluate_sequence(directory, config, args.frames, args.sre, anchor))
        if not args.json:
            print(f"  {Path(directory).name} done", file=sys.stderr, flush=True)
    summary: dict[str, Any] = {"tracker": features.value, "silhouette": silhouette.value}
    if args.param:
        named = _named(args.param)
        summary["params"] = {k: str(v) for k, v in sorted(vars(config).items()) if k in named}
        summary["params"].update(
            {ANCHOR_PREFIX + k: str(v) for k, v in sorted(vars(anchor).items()) if ANCHOR_PREFIX + k in named}
        )
    if len(sequences) == 1:
        summary.update(sequences[0])
    else:
        summary["sequences"] = sequences
        summary.update(_means(sequences))
        every = [t for s in sequences for t in s["targets"]]
        summary["targets_mean"] = _means(every)
    if args.json:
        print(dumps_json(summary, sort_keys=True))
        return 0
    overrides = "".join(f", {k}={v}" for k, v in summary.get("params", {}).items())
    print(f"tracker {features.value}, silhouette {silhouette.value}{overrides}")
    sre = " SRE@20 SRE-AUC" if args.sre else ""
    print(f"{'target':<14} {'frames':>6} {'prec@20':>8} {'AUC':>6} {'fps':>7} {'occluded':>8}{sre}")

    def line(name: str, row: dict[str, Any], occluded: str) -> str:
        text = (
            f"{name:<14} {row['frames']:>6} {row['precision_20px']:>8.3f} {row['success_auc']:>6.3f} "
            f"{row['fps']:>7.0f} {occluded:>8}"
        )
        if args.sre:
            text += f" {row['sre_precision_20px']:>6.3f} {row['sre_success_auc']:>7.3f}"
        return text

    for s in sequences:
        for t in s["targets"]:
            print(line(t["target"], t, str(t["occluded_frames"])))
        if len(s["targets"]) > 1:
            print(line(f"{s['sequence']} (mean)", s, ""))
    if len(sequences) > 1:
        print(line("mean (seq.)", summary, ""))
    return 0
