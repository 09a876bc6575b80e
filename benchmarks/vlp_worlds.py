"""VLP on the hard ceilings of issue 19: ``vlp-agent eval vlp`` on every acceptance world, seeds 0-2.

Each case is a world file of ``examples/worlds/`` (and a speed: ``drive15`` is driven across at 1.5 m/s,
the rest are the static test). Every run is the wizard's calibration, then ``eval vlp`` itself, in this
process. The agent's view is the world's nominal camera and surveyed LED map. First the wizard's
``row-time`` step (``calibration.row_time``): 30 frames of the world rendered where the simulated robot
takes them (under the middle of the three LEDs nearest its start, at three headings), every LED's stripe
period fitted, the LEDs recognised together and the row time estimated (``estimate_from_frames``); when
the step's checks pass, its row time replaces the nominal one (``eval vlp --t-row-s``), as its advice
says to put it in the robot config. Then ``eval vlp`` (``agent.commands.eval_vlp.evaluate``) runs the
``vlp-error`` step's calibration (a turn in place for the principal point and the mount tilt, then fixes
at known points for the residual correction, validated on held-out points) and scores the calibrated
pipeline. Per world, over its seeds (every frame, not only the nominal fixes):

- ``fix_fraction``: frames with a fix (nominal or degraded) over all frames;
- ``mean_error_cm``, ``p90_error_cm``, ``max_error_cm``: errors of the nominal (not degraded) fixes;
- ``unflagged_over_5cm``: nominal fixes more than 5 cm off (a wrong fix passed as good);
- ``protection_coverage``: nominal fixes whose protection level is at least their error, over all of them;
- ``frame_ms_max``: the longest time the pipeline took on one frame (wall time, on a shared machine);
- ``exception``: an uncaught exception of ``eval vlp``, if any (its type and message).

A world passes the issue's acceptance when no run raised, ``unflagged_over_5cm`` is 0 and
``protection_coverage`` is at least 0.999 of the nominal fixes. A world with no nominal fix at all passes
them vacuously: its row says so in ``notes`` (every fix degraded is honest, but no use to a
controller). ``env1`` also keeps Environment 1's figures: mean <= 0.15 cm, p90 <= 0.25 cm, id accuracy
per track 1.0. The max-time-per-frame target (20 ms with 12 LEDs of a 4-signature map in view) is
``benchmarks/vlp_association.py``'s; here it is reported, not judged.

Prints one JSON object: ``table`` (per world exactly ``fix_fraction``, ``mean_error_cm``,
``p90_error_cm``, ``max_error_cm``, ``unflagged_over_5cm``, ``protection_coverage``, ``frame_ms_max``, to
paste), ``row_time`` (per world the calibrated row time against the truth, per seed), ``pass``,
``failed``, ``notes``; with ``--details`` also every world's full row (flags, refusals, nominal and
degraded counts, ids). Progress goes to stderr.

    .venv/bin/python benchmarks/vlp_worlds.py [--seeds 0 1 2] [--worlds env1 sig100 ...] [--points N]
        [--repeats N] [--no-row-time] [--details]
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agent.commands.eval_vlp import evaluate
from agent.sim_view import agent_view
from calibration.row_time import (
    MAX_LED_DEVIATION,
    MAX_RELATIVE_SIGMA,
    MIN_LEDS,
    capture_poses,
    estimate_from_frames,
)
from drivers.sim.render import RollingShutterRenderer
from drivers.sim.world import Pose2D
from drivers.sim.worldfile import load_world

WORLDS = Path(__file__).resolve().parents[1] / "examples" / "worlds"

# (case name, world file stem, speed m/s, the odometry prior's sigma (m, deg) where the map repeats ids, None:
# eval vlp's 0.2 m / 10 deg): the conditions of issue 19's acceptance, then the world file's other
# real-ceiling conditions, then Environment 1 itself (whose figures must hold).
# dense_repeats is run twice. With eval vlp's prior (0.2 m, 10 deg, stated at twice that) it has no nominal
# fix, rightly: every LED's id recurs 1.0 m away, so the whole view fits again 1.0 m off, and a prior stated
# at 0.4 m cannot rule that placement out at the integrity risk ((1.0 / 0.4)^2 = 6.25 against the 3-dof
# chi-square quantile 16.3 at 1e-3: it would need a stated sigma under 0.25 m). dense_repeats_p5cm gives
# the prior of a robot that knows where it starts (the fusion's initial_sigma_xy_m, 5 cm; stated 10 cm),
# which is what the runtime passes once VLP is fused: there the fixes are nominal and must be right.
CASES: tuple[tuple[str, str, float, tuple[float, float] | None], ...] = (
    ("dense_repeats", "dense_repeats", 0.0, None),
    ("dense_repeats_p5cm", "dense_repeats", 0.0, (0.05, 5.0)),
    ("sig100", "sig100", 0.0, None),
    ("short_stripes", "short_stripes", 0.0, None),
    ("sparse", "sparse", 0.0, None),
    ("pairs13", "pairs13", 0.0, None),
    ("survey25", "survey25", 0.0, None),
    ("tilt15", "tilt15", 0.0, None),
    ("low_signal", "low_signal", 0.0, None),
    ("row_time3", "row_time3", 0.0, None),
    ("dead_led", "dead_led", 0.0, None),
    ("drive15", "drive15", 1.5, None),
    ("stray_light", "stray_light", 0.0, None),
    ("jpeg", "jpeg", 0.0, None),
    ("occluders", "occluders", 0.0, None),
    ("unmapped", "unmapped", 0.0, None),
    ("camera_errors", "camera_errors", 0.0, None),
    ("led_drift", "led_drift", 0.0, None),
    ("sig100_row3", "sig100_row3", 0.0, None),
    ("env1", "env1", 0.0, None),
)

UNFLAGGED_ALLOWED = 0
COVERAGE_MIN = 0.999
ENV1_MEAN_CM, ENV1_P90_CM, ENV1_IDS = 0.15, 0.25, 1.0

log = logging.getLogger("vlp_worlds")


# The row-time step's capture: frames (the step's default) and the gap between them (the camera's rate).
ROW_TIME_FRAMES = 30
ROW_TIME_SEED_OFFSET = 100


@dataclass
class RowTime:
    """The wizard's row-time step on one seed's capture: the row time it found (None: no estimate), its
    relative uncertainty, whether its checks passed (then it is applied), and why not."""

    nominal_s: float
    true_s: float
    found_s: float | None = None
    relative_sigma: float = math.nan
    applied: bool = False
    refused: str | None = None
    retried: str | None = None
    frames: int = ROW_TIME_FRAMES

    def as_json(self) -> dict[str, Any]:
        return {
            "nominal_us": round(1e6 * self.nominal_s, 4),
            "true_us": round(1e6 * self.true_s, 4),
            "calibrated_us": round(1e6 * self.found_s, 4) if self.found_s is not None else None,
            "error_pct": round(100.0 * (self.found_s / self.true_s - 1.0), 3) if self.found_s else None,
            "sigma_pct": _nan_to_none(100.0 * self.relative_sigma),
            "applied": self.applied,
            "refused": self.refused,
            "frames": self.frames,
            "first_try_refused": self.retried,
        }


def calibrate_row_time(stem: str, seed: int) -> RowTime:
    """The wizard's ``row-time`` step on the simulated robot of world ``stem``: ``ROW_TIME_FRAMES`` frames
    at ``calibration.row_time.capture_poses`` (a third at each heading), measured by the step's own
    ``estimate_from_frames``; applied when the step's checks pass. When only its uncertainty check fails,
    the step is run again with three times the frames (``--frames 90``), as one would on the robot."""
    out = _row_time_step(stem, seed, ROW_TIME_FRAMES)
    if not out.applied and out.found_s is not None and out.refused and out.refused.startswith("uncertainty"):
        again = _row_time_step(stem, seed + 1000, 3 * ROW_TIME_FRAMES)
        again.retried = out.refused
        return again
    return out


def _row_time_step(stem: str, seed: int, n_frames: int) -> RowTime:
    """One run of the step with ``n_frames`` frames."""
    world = load_world(WORLDS / f"{stem}.toml")
    view = agent_view(world)
    renderer = RollingShutterRenderer.for_world(world, seed=seed + ROW_TIME_SEED_OFFSET)
    start = world.robot.start
    poses = capture_poses(view.led_map, (start.x_m, start.y_m, start.yaw_rad), view.mount)
    frames: list[Any] = []
    t = 500.0
    for k, (x, y, yaw) in enumerate(poses):
        count = n_frames // len(poses) if k < len(poses) - 1 else n_frames - len(frames)
        pose = Pose2D(x, y, yaw)

        def standing(_t: float, p: Pose2D = pose) -> Pose2D:
            return p

        for _ in range(count):
            frames.append(renderer.render(standing, t).image)
            t += 1.0 / world.camera.frame_rate_hz
        t += 2.0
    out = RowTime(view.intrinsics.t_row_s, world.camera.t_row_s, frames=n_frames)
    estimate, sightings = estimate_from_frames(frames, view.intrinsics, view.led_map, view.mount)
    if estimate is None:
        out.refused = sightings.refused or f"no LED recognised ({sightings.unknown} blobs)"
        return out
    out.found_s, out.relative_sigma = estimate.t_row_s, estimate.relative_sigma
    worst = max((abs(v) for v in estimate.led_deviation().values()), default=math.inf)
    if estimate.relative_sigma > MAX_RELATIVE_SIGMA:
        out.refused = f"uncertainty {100 * estimate.relative_sigma:.3f} % > {100 * MAX_RELATIVE_SIGMA} %"
    elif len(estimate.per_led) < MIN_LEDS:
        out.refused = f"{len(estimate.per_led)} LED recognised, {MIN_LEDS} needed"
    elif worst > MAX_LED_DEVIATION:
        out.refused = f"an LED's own row time {100 * worst:.2f} % off the estimate"
    else:
        out.applied = True
    return out


@dataclass
class Seeded:
    """What one seed's run of ``eval vlp`` gave."""

    seed: int
    frames: int = 0
    fixed: int = 0
    errors_m: tuple[float, ...] = ()
    degraded_errors_m: tuple[float, ...] = ()
    protected: int = 0
    unflagged: int = 0
    frame_ms_max: float = math.nan
    frame_cpu_ms_max: float = math.nan
    id_accuracy_track: float = math.nan
    degraded: int = 0
    flags: dict[str, int] | None = None
    no_fix: dict[str, int] | None = None
    calibration_refused: tuple[str, ...] = ()
    exception: str | None = None
    wall_s: float = 0.0
    row_time: RowTime | None = None


def run_one(
    stem: str,
    speed: float,
    seed: int,
    points: int,
    repeats: int,
    row_time: bool,
    prior_sigma: tuple[float, float] | None = None,
) -> Seeded:
    t0 = time.perf_counter()
    rt: RowTime | None = None
    if row_time:
        try:
            rt = calibrate_row_time(stem, seed)
        except Exception as exc:  # the wizard's step raising is a failure of the benchmark's world too
            log.error("%s seed %d: row-time step: %s\n%s", stem, seed, exc, traceback.format_exc())
            return Seeded(
                seed, exception=f"row-time: {type(exc).__name__}: {exc}", wall_s=time.perf_counter() - t0
            )
        if not rt.applied:
            log.warning("%s seed %d: row-time calibration not applied: %s", stem, seed, rt.refused)
    args = argparse.Namespace(
        world=str(WORLDS / f"{stem}.toml"),
        points=points,
        repeats=repeats,
        speed=speed,
        seed=seed,
        json=True,
        png=None,
        calibration_out=None,
        area=None,
        t_row_s=rt.found_s if rt is not None and rt.applied else None,
        prior_sigma=list(prior_sigma) if prior_sigma is not None else None,
    )
    try:
        summary, cal, _, _ = evaluate(args)
    except Exception as exc:  # an uncaught exception of eval vlp is what this benchmark looks for
        log.error("%s seed %d: %s\n%s", stem, seed, exc, traceback.format_exc())
        return Seeded(
            seed, exception=f"{type(exc).__name__}: {exc}", wall_s=time.perf_counter() - t0, row_time=rt
        )
    calib = summary["calibration"]
    refused = tuple(
        f"{key}: {calib[key]}" for key in ("rotation_centre_refused", "residual_refused") if calib[key]
    )
    return Seeded(
        seed,
        frames=summary["frames"],
        fixed=len(cal.errors_m) + len(cal.degraded_errors_m),
        errors_m=tuple(cal.errors_m),
        degraded_errors_m=tuple(cal.degraded_errors_m),
        protected=cal.protected,
        unflagged=cal.unflagged_over_5cm,
        frame_ms_max=summary["frame_ms_max"],
        frame_cpu_ms_max=summary["frame_cpu_ms_max"],
        id_accuracy_track=summary["id_accuracy_track"],
        degraded=len(cal.degraded_errors_m),
        flags=summary["flags"],
        no_fix=summary["no_fix"],
        calibration_refused=refused,
        wall_s=time.perf_counter() - t0,
        row_time=rt,
    )


def _nan_to_none(value: float) -> float | None:
    return None if not math.isfinite(value) else round(value, 4)


def row(name: str, speed: float, runs: list[Seeded]) -> dict[str, Any]:
    """One world's line of the table: its seeds pooled, and whether it passes."""
    errors_cm = 100.0 * np.array([e for r in runs for e in r.errors_m], dtype=np.float64)
    frames = sum(r.frames for r in runs)
    nominal = errors_cm.size
    coverage = sum(r.protected for r in runs) / nominal if nominal else math.nan
    unflagged = sum(r.unflagged for r in runs)
    exceptions = [f"seed {r.seed}: {r.exception}" for r in runs if r.exception]
    reasons = []
    if exceptions:
        reasons.append("uncaught exception")
    if unflagged > UNFLAGGED_ALLOWED:
        reasons.append(f"{unflagged} unflagged fixes over 5 cm")
    if nominal and coverage < COVERAGE_MIN:
        reasons.append(f"protection coverage {coverage:.4f} < {COVERAGE_MIN}")
    mean = float(errors_cm.mean()) if nominal else math.nan
    p90 = float(np.percentile(errors_cm, 90)) if nominal else math.nan
    ids = [r.id_accuracy_track for r in runs if math.isfinite(r.id_accuracy_track)]
    id_track = min(ids) if ids else math.nan
    if name == "env1" and not (mean <= ENV1_MEAN_CM and p90 <= ENV1_P90_CM and id_track >= ENV1_IDS):
        reasons.append(
            f"Environment 1's figures: mean {mean:.3f} cm (<= {ENV1_MEAN_CM}), p90 {p90:.3f} cm "
            f"(<= {ENV1_P90_CM}), ids {id_track:.3f} (>= {ENV1_IDS})"
        )
    degraded_cm = 100.0 * np.array([e for r in runs for e in r.degraded_errors_m], dtype=np.float64)
    notes = []
    if not nominal:
        notes.append("no nominal fix: the integrity criteria hold vacuously (every fix degraded or none)")
    elif nominal < 0.2 * frames:
        notes.append(f"few nominal fixes ({nominal} of {frames} frames)")
    flags: dict[str, int] = {}
    no_fix: dict[str, int] = {}
    for r in runs:
        for key, n in (r.flags or {}).items():
            flags[key] = flags.get(key, 0) + n
        for key, n in (r.no_fix or {}).items():
            no_fix[key] = no_fix.get(key, 0) + n
    return {
        "speed_mps": speed,
        "seeds": [r.seed for r in runs],
        "frames": frames,
        "fix_fraction": _nan_to_none(sum(r.fixed for r in runs) / frames if frames else math.nan),
        "nominal_fixes": nominal,
        "degraded_fixes": sum(r.degraded for r in runs),
        "degraded_median_error_cm": _nan_to_none(
            float(np.median(degraded_cm)) if degraded_cm.size else math.nan
        ),
        "degraded_max_error_cm": _nan_to_none(float(degraded_cm.max()) if degraded_cm.size else math.nan),
        "mean_error_cm": _nan_to_none(mean),
        "p90_error_cm": _nan_to_none(p90),
        "max_error_cm": _nan_to_none(float(errors_cm.max()) if nominal else math.nan),
        "unflagged_over_5cm": unflagged,
        "protection_coverage": _nan_to_none(coverage),
        "frame_ms_max": _nan_to_none(max((r.frame_ms_max for r in runs if r.frames), default=math.nan)),
        "frame_cpu_ms_max": _nan_to_none(
            max((r.frame_cpu_ms_max for r in runs if r.frames), default=math.nan)
        ),
        "id_accuracy_track_min": _nan_to_none(id_track),
        "flags": flags,
        "no_fix": no_fix,
        "calibration_refused": sorted({c for r in runs for c in r.calibration_refused}),
        "row_time": [r.row_time.as_json() if r.row_time else None for r in runs],
        "exceptions": exceptions,
        "wall_s": round(sum(r.wall_s for r in runs), 1),
        "pass": not reasons,
        "fails": reasons,
        "notes": notes,
    }


TABLE_COLUMNS = (
    "fix_fraction",
    "mean_error_cm",
    "p90_error_cm",
    "max_error_cm",
    "unflagged_over_5cm",
    "protection_coverage",
    "frame_ms_max",
)


def main() -> int:
    names = [c[0] for c in CASES]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds (default 0 1 2)")
    parser.add_argument("--worlds", nargs="+", choices=names, default=names, help="cases (default all)")
    parser.add_argument("--points", type=int, default=36, help="eval vlp --points (default 36)")
    parser.add_argument("--repeats", type=int, default=12, help="eval vlp --repeats (default 12)")
    parser.add_argument(
        "--no-row-time",
        action="store_true",
        help="skip the wizard's row-time step (evaluate with the nominal row time, as before)",
    )
    parser.add_argument("--details", action="store_true", help="also print every world's full row")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    log.setLevel(logging.INFO)
    table: dict[str, dict[str, Any]] = {}
    t0 = time.perf_counter()
    for name, stem, speed, prior_sigma in CASES:
        if name not in args.worlds:
            continue
        runs = []
        for seed in args.seeds:
            runs.append(
                run_one(stem, speed, seed, args.points, args.repeats, not args.no_row_time, prior_sigma)
            )
            rt = runs[-1].row_time
            log.info(
                "%s seed %d: %.1f s%s",
                name,
                seed,
                runs[-1].wall_s,
                f", row time {rt.as_json()}" if rt is not None else "",
            )
        table[name] = row(name, speed, runs)
        r = table[name]
        log.info(
            "%s: %s fix %.3f, nominal %d, mean/p90/max %s/%s/%s cm, unflagged %d, coverage %s, %s %s",
            name,
            "PASS" if r["pass"] else "FAIL",
            r["fix_fraction"] or 0.0,
            r["nominal_fixes"],
            r["mean_error_cm"],
            r["p90_error_cm"],
            r["max_error_cm"],
            r["unflagged_over_5cm"],
            r["protection_coverage"],
            "; ".join(r["fails"]),
            "; ".join(r["notes"]),
        )
    report: dict[str, Any] = {
        "benchmark": "vlp_worlds",
        "seeds": args.seeds,
        "points": args.points,
        "repeats": args.repeats,
        "row_time_step": not args.no_row_time,
        "acceptance": {
            "unflagged_over_5cm": UNFLAGGED_ALLOWED,
            "protection_coverage_min": COVERAGE_MIN,
            "env1": {"mean_cm_max": ENV1_MEAN_CM, "p90_cm_max": ENV1_P90_CM, "id_accuracy_track": ENV1_IDS},
        },
        "table": {n: {c: r[c] for c in TABLE_COLUMNS} for n, r in table.items()},
        "nominal_fixes": {n: r["nominal_fixes"] for n, r in table.items()},
        # frame_ms_max is wall time (a loaded machine's); the pipeline's own CPU time per frame, at most:
        "frame_cpu_ms_max": {n: r["frame_cpu_ms_max"] for n, r in table.items()},
        "row_time": {n: r["row_time"] for n, r in table.items()},
        "passed": [n for n, r in table.items() if r["pass"]],
        "failed": {n: r["fails"] for n, r in table.items() if not r["pass"]},
        "notes": {n: r["notes"] for n, r in table.items() if r["notes"]},
        "pass": all(r["pass"] for r in table.values()),
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    if args.details:
        report["worlds"] = table
    print(json.dumps(report, indent=1, allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
