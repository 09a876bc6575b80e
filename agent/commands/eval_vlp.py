"""``vlp-agent eval vlp``: VLP accuracy, id accuracy and latency on a simulated world, calibration included.

What it does, in the order a robot would live it:

1. **The agent's view.** The pipeline is built from the world's *nominal* camera and *surveyed* LED map
   (``drivers.sim.worldfile.nominal_camera`` / ``surveyed_leds``): principal point, LED positions and heights
   off by the world's ``[errors]``, camera tilt unknown. Frames are rendered by the physical renderer from the
   *true* world.
2. **Calibration, as on the robot** (``agent.vlp.calibration``). The robot turns in place once under the LEDs,
   30 % of the way into the test area from its south-west corner (so the LEDs are at different distances from
   the axis); the circles its LED tracks draw give the principal point and the camera's tilt on its mount.
   Then fixes at a grid of known points (four headings each) give the residual correction. The result is
   written to a calibration file (TOML, docs/vlp.md) and read back from it: nothing true is handed over.
3. **The test** (static, ``--speed 0``): ``--points`` random places in the test area (the LED map's bounding
   box; at least two LEDs fully in view), random heading, ``--repeats`` consecutive frames each (the
   paper's 36 x 12). Each frame goes through an uncalibrated and a calibrated pipeline. The dispersion circle
   (the paper's Fig. 8) is measured at the area's centre over twelve headings.
   **Driving** (``--speed`` > 0): ``--points`` straight passes across the area at that speed, frames at the
   camera's rate, with motion during the rolling readout; the pipeline runs continuously on each pass (with
   an odometry-grade prior on every frame when the map repeats ids).
4. **Scores.** Position error of the base at each frame's mid-readout time; id accuracy per frame (the
   frame's own stripes) and per track (after voting), over every fully visible LED the pipeline reports,
   checked against the renderer's ground truth; latency of the calibrated pipeline per frame and per stage,
   on one core (``cv2.setNumThreads(1)``).

Prints one JSON object with ``--json``; otherwise a table, and a PNG of estimated vs true positions with the
error CDFs (the paper's Fig. 9).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from agent import figure
from agent.commands.args import dumps_json
from agent.commands.worlds import EXAMPLES
from agent.sim_view import agent_view
from agent.vlp.calibration import (
    ResidualCorrection,
    VlpCalibration,
    fit_rotation_centre,
    format_calibration,
    mount_tilt_from_shift,
    parse_calibration,
    validated_residual_correction,
)
from agent.vlp.model import (
    Motion,
    PosePrior,
    VlpFix,
    VlpResult,
)
from agent.vlp.pipeline import VlpPipeline
from drivers.errors import ConfigError
from drivers.sim.render import FrameTruth, RenderedFrame, RollingShutterRenderer
from drivers.sim.world import Pose2D, World
from drivers.sim.worldfile import load_world, map_indices

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
PoseAt = Callable[[float], Pose2D]

DEFAULT_WORLD = EXAMPLES / "env1.toml"
# Turning in place for the rotation-centre calibration (a TurtleBot3 turns at up to 2.8 rad/s).
CALIBRATION_TURN_RADPS = 0.5
TURN_AT = 0.3
# Known points for the residual correction: a 3 x 3 grid over the inner part of the area, four headings.
CALIBRATION_GRID = 3
CALIBRATION_HEADINGS = 4
CALIBRATION_FRAMES = 3
# The dispersion circle: headings at the area's centre, frames per heading.
DISPERSION_HEADINGS = 12
DISPERSION_FRAMES = 3
# Driving passes: straight, at most this long (the whole area in Environment 1).
PASS_LENGTH_M = 4.0
# The odometry-grade prior given when the map repeats ids (what the robot's odometry or last fix would know).
PRIOR_SIGMA_XY_M = 0.2
PRIOR_SIGMA_YAW_RAD = math.radians(10.0)
# Driving, the base's velocity from wheel odometry (what the runtime passes the pipeline with its prior, for
# the rolling-shutter correction): off by this fraction of the speed, and this much yaw rate (1 sigma).
ODOMETRY_SPEED_SIGMA = 0.02
ODOMETRY_YAW_RATE_SIGMA_RADPS = 0.02
# A nominal (not degraded) fix farther than this from the truth is a wrong fix passed as good.
UNFLAGGED_LIMIT_M = 0.05


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "vlp",
        help="VLP accuracy, id accuracy and latency on a simulated world (with its calibration)",
        description="Render frames of a simulated world at known poses, calibrate the camera as on the "
        "robot (turn in place; fixes at known points), then measure the VLP pipeline: position error before "
        "and after calibration, id accuracy per frame and per track, the dispersion circle, and latency per "
        "frame and per stage on one core.",
    )
    p.add_argument("--world", metavar="FILE", help=f"world file (default: {DEFAULT_WORLD.name})")
    p.add_argument("--points", type=int, default=36, help="test points, or passes when driving (default 36)")
    p.add_argument("--repeats", type=int, default=12, help="frames per static test point (default 12)")
    p.add_argument(
        "--speed", type=float, default=0.0, metavar="M_PER_S", help="drive across the area at this speed"
    )
    p.add_argument("--seed", type=int, default=0, help="seed for poses, noise and LED phases (default 0)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    p.add_argument("--png", metavar="FILE", help="where to write the figure (default: vlp_eval_<world>.png)")
    p.add_argument("--calibration-out", metavar="FILE", help="keep the calibration file written here")
    p.add_argument(
        "--prior-sigma",
        type=float,
        nargs=2,
        metavar=("XY_M", "YAW_DEG"),
        help="where the map repeats ids, the error (1 sigma) of the odometry-grade pose prior given on each "
        "run's first frame, stated to the pipeline at twice this (default 0.2 m, 10 deg)",
    )
    p.add_argument(
        "--t-row-s",
        type=float,
        metavar="SECONDS",
        help="the camera's row time as calibrated (`vlp-agent calibrate row-time`'s t_row_s), in place of "
        "the world's nominal one (default: the nominal one)",
    )
    p.add_argument(
        "--area",
        type=float,
        nargs=4,
        metavar=("X0", "Y0", "X1", "Y1"),
        help="test area in metres (default: the LED map's bounding box)",
    )


def default_area(world: World) -> tuple[float, float, float, float]:
    xs = [led.x_m for led in world.leds]
    ys = [led.y_m for led in world.leds]
    if not xs:
        raise ConfigError("leds", "the world has no LEDs to position from", world.source)
    return min(xs), min(ys), max(xs), max(ys)


def leds_in_view(renderer: RollingShutterRenderer, pose: Pose2D, margin_px: float) -> int:
    """How many lit LED disks (mapped or not) are entirely inside the image, ``margin_px`` from its border,
    at ``pose``."""
    cam = renderer.camera
    mount = renderer.mount
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    lens_x = pose.x_m + c * mount.x_m - s * mount.y_m
    lens_y = pose.y_m + s * mount.x_m + c * mount.y_m
    yaw = pose.yaw_rad + mount.yaw_rad
    count = 0
    for led in renderer.leds:
        if led.dead:
            continue
        u, v, depth = renderer.project(
            np.array([led.x_m]), np.array([led.y_m]), np.array([led.z_m]), lens_x, lens_y, yaw
        )
        if depth[0] <= 0:
            continue
        uo, vo = renderer.sensor_to_output(float(u[0]), float(v[0]))
        r = renderer.output_intrinsics.fx_px * led.diameter_m / 2.0 / float(depth[0])
        if r + margin_px < uo < cam.output_width_px - r - margin_px and (
            r + margin_px < vo < cam.output_height_px - r - margin_px
        ):
            count += 1
    return count


# -- scoring -------------------------------------------------------------------------------------------------
@dataclass
class Tally:
    """Errors, id checks and timings of one pipeline over a run."""

    errors_m: list[float] = field(default_factory=list)
    fixes: list[tuple[float, float, float, float]] = field(default_factory=list)  # est x, y, true x, y
    no_fix: Counter[str] = field(default_factory=Counter)
    degraded_errors_m: list[float] = field(default_factory=list)
    # Nominal fixes whose protection level is at least their error; nominal fixes more than 5 cm off.
    protected: int = 0
    unflagged_over_5cm: int = 0
    flags: Counter[str] = field(default_factory=Counter)
    ids_seen: int = 0
    ids_decoded: int = 0
    ids_frame_ok: int = 0
    # Frames whose stripes named an id, and how many named a wrong one; refusals by their code.
    ids_named: int = 0
    ids_named_wrong: int = 0
    refusals: Counter[str] = field(default_factory=Counter)
    ids_settled: int = 0
    ids_track_ok: int = 0
    assoc_seen: int = 0
    assoc_ok: int = 0
    tracks_final: dict[int, tuple[str, str | None]] = field(default_factory=dict)
    # Each world LED's index in the agent's map (None: missing from it), for checking the association.
    map_index: Sequence[int | None] = ()
    latency_ms: list[float] = field(default_factory=list)
    # The thread's CPU time per frame (what waiting for a core on a shared machine leaves out).
    cpu_ms: list[float] = field(default_factory=list)
    stage_ms: dict[str, list[float]] = field(
        default_factory=lambda: {"acquire": [], "track": [], "decode": [], "solve": []}
    )

    def add(self, result: VlpResult, truth: FrameTruth, cpu_ms: float | None = None) -> None:
        t = result.timings
        self.latency_ms.append(t.total_ms)
        if cpu_ms is not None:
            self.cpu_ms.append(cpu_ms)
        for name, value in (("acquire", t.acquire_ms), ("track", t.track_ms), ("decode", t.decode_ms)):
            self.stage_ms[name].append(value)
        self.stage_ms["solve"].append(t.solve_ms)
        base = truth.base_pose
        if isinstance(result, VlpFix):
            err = math.hypot(result.x_m - base.x_m, result.y_m - base.y_m)
            self.flags.update(result.flags)
            if result.degraded:
                # A degraded fix (one LED and the prior's yaw, an outlier dropped) says so; it is scored
                # apart, as a consumer weighs it by its covariance.
                self.degraded_errors_m.append(err)
            else:
                self.errors_m.append(err)
                self.fixes.append((result.x_m, result.y_m, base.x_m, base.y_m))
                self.protected += int(result.protection_level_m >= err)
                self.unflagged_over_5cm += int(err > UNFLAGGED_LIMIT_M)
        else:
            self.no_fix[result.reason] += 1
        for obs in result.leds:
            if obs.visibility != "full":
                continue
            near = [
                lt
                for lt in truth.leds
                if lt.in_image and math.dist(lt.centre_px, obs.centre_px) < max(0.5 * lt.radius_px, 2.0)
            ]
            if not near:
                continue
            lt = near[0]
            self.ids_seen += 1
            if obs.frame_id is not None or obs.id is None:
                # Decoded on this frame (a settled track is only verified every few frames); an undecided
                # frame of an unsettled track counts as wrong.
                self.ids_decoded += 1
                self.ids_frame_ok += int(obs.frame_id == lt.id)
            if obs.frame_id is not None:
                self.ids_named += 1
                self.ids_named_wrong += int(obs.frame_id != lt.id)
            if obs.frame_reason:
                self.refusals[obs.frame_reason.split(":")[0]] += 1
            if obs.id is not None:
                self.ids_settled += 1
                self.ids_track_ok += int(obs.id == lt.id)
            self.tracks_final[obs.track_id] = (lt.id, obs.id)
            if obs.map_index is not None:
                self.assoc_seen += 1
                truth_index = self.map_index[lt.index] if self.map_index else lt.index
                self.assoc_ok += int(obs.map_index == truth_index)


def _pct(values: Sequence[float], q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else math.nan


def _summary_errors(errors_m: Sequence[float]) -> dict[str, float]:
    cm = [100.0 * e for e in errors_m]
    return {
        "mean_error_cm": float(np.mean(cm)) if cm else math.nan,
        "median_error_cm": _pct(cm, 50),
        "p90_error_cm": _pct(cm, 90),
        "max_error_cm": float(np.max(cm)) if cm else math.nan,
    }


# -- running a pipeline over frames --------------------------------------------------------------------------
class Bench:
    """The world, its renderer and the agent's view, with helpers to render and process frames."""

    def __init__(self, world: World, seed: int) -> None:
        self.world = world
        self.view = agent_view(world)
        self.renderer = RollingShutterRenderer.for_world(world, seed=seed)
        self.fps = world.camera.frame_rate_hz
        self.rng = np.random.default_rng(seed + 1)
        self.map_index = map_indices(world)
        self.repeats_ids = not self.view.led_map.ids_unique
        self.margin_px = 20.0 / 800.0 * world.camera.output_width_px
        self.clock = 1000.0
        # The odometry-grade prior's error (1 sigma; it is stated at twice this).
        self.prior_sigma_xy_m = PRIOR_SIGMA_XY_M
        self.prior_sigma_yaw_rad = PRIOR_SIGMA_YAW_RAD

    def tally(self) -> Tally:
        return Tally(map_index=self.map_index)

    def frame(self, pose_at: PoseAt, t0: float) -> RenderedFrame:
        return self.renderer.render(pose_at, t0)

    def next_start(self, span_s: float) -> float:
        """A fresh stretch of simulated time (frames of different runs never share a time)."""
        start = self.clock + float(self.rng.uniform(0.0, 1.0))
        self.clock = start + span_s + 10.0
        return start

    def prior_for(self, pose: Pose2D) -> PosePrior | None:
        """An odometry-grade prior when the map repeats ids (unneeded otherwise)."""
        if not self.repeats_ids:
            return None
        return PosePrior(
            pose.x_m + float(self.rng.normal(0.0, self.prior_sigma_xy_m)),
            pose.y_m + float(self.rng.normal(0.0, self.prior_sigma_xy_m)),
            pose.yaw_rad + float(self.rng.normal(0.0, self.prior_sigma_yaw_rad)),
            2.0 * self.prior_sigma_xy_m,
            2.0 * self.prior_sigma_yaw_rad,
        )

    def motion_for(self, vx_mps: float, vy_mps: float, yaw_rate_radps: float) -> Motion:
        """The base's velocity as odometry gives it: the true one off by ``ODOMETRY_SPEED_SIGMA`` of the
        speed (a wheel-radius error, slip) and ``ODOMETRY_YAW_RATE_SIGMA_RADPS``."""
        scale = 1.0 + float(self.rng.normal(0.0, ODOMETRY_SPEED_SIGMA))
        return Motion(
            vx_mps * scale,
            vy_mps * scale,
            yaw_rate_radps + float(self.rng.normal(0.0, ODOMETRY_YAW_RATE_SIGMA_RADPS)),
        )

    def random_pose(self, area: tuple[float, float, float, float], min_leds: int = 2) -> Pose2D:
        x0, y0, x1, y1 = area
        for _ in range(10_000):
            pose = Pose2D(
                float(self.rng.uniform(x0, x1)),
                float(self.rng.uniform(y0, y1)),
                float(self.rng.uniform(-math.pi, math.pi)),
            )
            if leds_in_view(self.renderer, pose, self.margin_px) >= min_leds:
                return pose
        raise ConfigError("--area", f"no pose in {area} sees {min_leds} LEDs", self.world.source)


def static_frames(
    bench: Bench,
    pose: Pose2D,
    count: int,
    pipelines: Sequence[VlpPipeline],
    tallies: Sequence[Tally],
) -> list[list[VlpResult]]:
    """``count`` consecutive frames of a robot standing at ``pose``, through each pipeline (reset first)."""
    for pipe in pipelines:
        pipe.reset()
    start = bench.next_start(count / bench.fps)
    prior = bench.prior_for(pose)
    out: list[list[VlpResult]] = [[] for _ in pipelines]
    for k in range(count):
        t0 = start + k / bench.fps + float(bench.rng.uniform(0.0, 1e-3))
        rendered = bench.frame(lambda t: pose, t0)
        for i, (pipe, tally) in enumerate(zip(pipelines, tallies, strict=True)):
            c0 = time.thread_time()
            result = pipe.process(rendered.image, rendered.truth.t_mid_s, prior=prior if k == 0 else None)
            tally.add(result, rendered.truth, 1e3 * (time.thread_time() - c0))
            out[i].append(result)
    return out


# -- calibration ---------------------------------------------------------------------------------------------
@dataclass
class CalibrationReport:
    calibration: VlpCalibration
    file: str
    turn_frames: int
    tracks_used: int
    known_fixes: int
    residual_refused: str | None = None
    rotation_centre_refused: str | None = None


def calibrate(bench: Bench, area: tuple[float, float, float, float], out_path: Path) -> CalibrationReport:
    """The robot's calibration, simulated: turn in place, then fixes at known points. Writes the file."""
    view = bench.view
    # 1. Rotation centre: one full turn in place, tracks of the uncalibrated pipeline. Off the area's middle
    # (TURN_AT of the way from its south-west corner), so that the LEDs are at different distances from the
    # axis: their circles' radii then tell the camera's tilt from a principal-point error.
    centre = Pose2D(area[0] + TURN_AT * (area[2] - area[0]), area[1] + TURN_AT * (area[3] - area[1]), 0.0)
    pipe = VlpPipeline(view.intrinsics, view.led_map, view.mount)
    duration = 2.0 * math.pi / CALIBRATION_TURN_RADPS
    n = int(duration * bench.fps) + 1
    start = bench.next_start(duration)

    def turning(t: float) -> Pose2D:
        return Pose2D(centre.x_m, centre.y_m, CALIBRATION_TURN_RADPS * (t - start))

    paths: dict[int, list[tuple[float, float]]] = {}
    heights: dict[int, float] = {}
    prior = bench.prior_for(centre)
    for k in range(n):
        rendered = bench.frame(turning, start + k / bench.fps)
        result = pipe.process(rendered.image, rendered.truth.t_mid_s, prior=prior if k == 0 else None)
        for obs in result.leds:
            if obs.visibility != "full":
                continue
            paths.setdefault(obs.track_id, []).append(obs.centre_px)
            if obs.map_index is not None:
                heights[obs.track_id] = view.led_map.leds[obs.map_index].z_m - view.mount.z_m
    ids = [k for k in paths if k in heights]
    rc = fit_rotation_centre(
        [np.array(paths[k]) for k in ids], [heights[k] for k in ids], view.intrinsics, view.mount
    )
    size = (view.intrinsics.width_px, view.intrinsics.height_px)
    if isinstance(rc, str):
        # A ceiling too sparse for the turn: the nominal principal point stays, the residual still runs.
        log.warning("calibration: no rotation centre, the nominal principal point is kept: %s", rc)
        centred = VlpCalibration(size)
    else:
        tilt = mount_tilt_from_shift(rc.tilt_px, view.intrinsics) if rc.tilt_px is not None else None
        centred = VlpCalibration(size, (rc.cx_px, rc.cy_px), rc.sigma_px, mount_tilt_rad=tilt)

    # 2. Residual correction: fixes at known points with the centre applied.
    pipe = VlpPipeline(view.intrinsics, view.led_map, view.mount, calibration=centred)
    est: list[tuple[float, float]] = []
    true: list[tuple[float, float]] = []
    x0, y0, x1, y1 = area
    tally = bench.tally()
    for i in range(CALIBRATION_GRID):
        for j in range(CALIBRATION_GRID):
            fx = (i + 0.5) / CALIBRATION_GRID
            fy = (j + 0.5) / CALIBRATION_GRID
            for h in range(CALIBRATION_HEADINGS):
                pose = Pose2D(
                    x0 + fx * (x1 - x0), y0 + fy * (y1 - y0), h * 2.0 * math.pi / CALIBRATION_HEADINGS
                )
                if leds_in_view(bench.renderer, pose, bench.margin_px) < 2:
                    continue
                (results,) = static_frames(bench, pose, CALIBRATION_FRAMES, [pipe], [tally])
                for r in results:
                    if isinstance(r, VlpFix) and not r.degraded:
                        est.append((r.x_m, r.y_m))
                        true.append((pose.x_m, pose.y_m))
    checked = validated_residual_correction(np.array(est), np.array(true), degree=1) if est else "no fixes"
    residual = checked if isinstance(checked, ResidualCorrection) else None
    refused = checked if isinstance(checked, str) else None
    if refused is not None:
        log.warning("calibration: no residual correction: %s", refused)
    calibration = dataclasses.replace(centred, residual=residual)
    text = format_calibration(
        calibration,
        f"world {bench.world.name}: rotation centre from a {duration:.1f} s turn in place at "
        f"({centre.x_m:.2f}, {centre.y_m:.2f}) m ({len(ids)} LED tracks); residual from {len(est)} fixes "
        f"at {CALIBRATION_GRID}x{CALIBRATION_GRID} known points x {CALIBRATION_HEADINGS} headings",
    )
    out_path.write_text(text, encoding="utf-8")
    principal = centred.principal_point_px or (view.intrinsics.cx_px, view.intrinsics.cy_px)
    log.info(
        "calibration: principal point (%.2f, %.2f) px from %d tracks, residual rms %.2f -> %.2f mm",
        principal[0],
        principal[1],
        len(ids),
        1e3 * (residual.rms_before_m if residual else math.nan),
        1e3 * (residual.rms_after_m if residual else math.nan),
    )
    loaded = parse_calibration(out_path.read_text(encoding="utf-8"), source=str(out_path))
    return CalibrationReport(
        loaded, str(out_path), n, len(ids), len(est), refused, rc if isinstance(rc, str) else None
    )


# -- the runs ------------------------------------------------------------------------------------------------
def dispersion(bench: Bench, pipe: VlpPipeline, centre: Pose2D) -> dict[str, float]:
    """The paper's dispersion circle at one spot: fixes over twelve headings; offset = |mean - truth|,
    radius = the largest distance of a fix from the mean."""
    tally = bench.tally()
    for h in range(DISPERSION_HEADINGS):
        yaw = (h + 0.37) * 2.0 * math.pi / DISPERSION_HEADINGS
        static_frames(bench, Pose2D(centre.x_m, centre.y_m, yaw), DISPERSION_FRAMES, [pipe], [tally])
    if not tally.fixes:
        return {"offset_cm": math.nan, "radius_cm": math.nan}
    est = np.array([(f[0], f[1]) for f in tally.fixes])
    mean = est.mean(axis=0)
    offset = math.hypot(mean[0] - centre.x_m, mean[1] - centre.y_m)
    radius = float(np.max(np.hypot(est[:, 0] - mean[0], est[:, 1] - mean[1])))
    return {"offset_cm": 100.0 * offset, "radius_cm": 100.0 * radius}


def driving(
    bench: Bench, pipe: VlpPipeline, area: tuple[float, float, float, float], passes: int, speed: float
) -> Tally:
    """Straight passes at ``speed``, each through a random point of the area at a random heading, as long
    as the area's diagonal (at most ``PASS_LENGTH_M``), frames at the camera's rate while inside the area."""
    tally = bench.tally()
    x0, y0, x1, y1 = area
    length = min(math.hypot(x1 - x0, y1 - y0), PASS_LENGTH_M)
    for _ in range(passes):
        through = bench.random_pose(area)
        heading = through.yaw_rad
        duration = length / speed
        start = bench.next_start(duration)
        t_mid = start + 0.5 * duration
        c, s = math.cos(heading), math.sin(heading)

        def pose_at(
            t: float,
            cx: float = through.x_m,
            cy: float = through.y_m,
            c: float = c,
            s: float = s,
            h: float = heading,
            tm: float = t_mid,
        ) -> Pose2D:
            d = speed * (t - tm)
            return Pose2D(cx + c * d, cy + s * d, h)

        pipe.reset()
        for k in range(int(duration * bench.fps)):
            t0 = start + k / bench.fps
            p = pose_at(t0)
            if not (x0 <= p.x_m <= x1 and y0 <= p.y_m <= y1):
                continue
            rendered = bench.frame(pose_at, t0)
            # Driving, the robot's odometry knows roughly where it is on every frame (the runtime passes the
            # fused pose as the prior); it matters only where the map repeats ids. Its velocity (the runtime
            # passes odometry's with the prior) is on every frame: the rolling-shutter correction needs it
            # from the first frame of a pass, and at 1.5 m/s a frame's LEDs are imaged up to 7 cm apart.
            prior = bench.prior_for(rendered.truth.base_pose)
            motion = bench.motion_for(speed * c, speed * s, 0.0)
            c0 = time.thread_time()
            result = pipe.process(rendered.image, rendered.truth.t_mid_s, prior=prior, motion=motion)
            tally.add(result, rendered.truth, 1e3 * (time.thread_time() - c0))
    return tally


def _ratio(num: int, den: int) -> float:
    return num / den if den else math.nan


def _stage_medians(t: Tally) -> dict[str, float]:
    return {name: _pct(values, 50) for name, values in t.stage_ms.items()}


def evaluate(args: argparse.Namespace) -> tuple[dict[str, Any], Tally, Tally, World]:
    world_path = Path(args.world) if args.world else DEFAULT_WORLD
    if not world_path.is_file():
        raise ConfigError("--world", f"no such world file: {world_path}")
    world = load_world(world_path)
    if args.points < 1 or args.repeats < 1:
        raise ConfigError("--points", "points and repeats must be >= 1")
    if args.speed < 0:
        raise ConfigError("--speed", f"must be >= 0, got {args.speed}")
    cv2.setNumThreads(1)
    bench = Bench(world, args.seed)
    t_row_s = getattr(args, "t_row_s", None)
    if t_row_s is not None:
        if not 0.0 < t_row_s < 1e-3:
            raise ConfigError("--t-row-s", f"must be between 0 and 1e-3 s, got {t_row_s}")
        # The row-time calibration's result, as the robot's config would carry it.
        bench.view = dataclasses.replace(
            bench.view, intrinsics=dataclasses.replace(bench.view.intrinsics, t_row_s=t_row_s)
        )
    prior_sigma = getattr(args, "prior_sigma", None)
    if prior_sigma is not None:
        if not (prior_sigma[0] > 0.0 and 0.0 < prior_sigma[1] <= 90.0):
            raise ConfigError("--prior-sigma", f"need XY_M > 0 and 0 < YAW_DEG <= 90, got {prior_sigma}")
        bench.prior_sigma_xy_m = float(prior_sigma[0])
        bench.prior_sigma_yaw_rad = math.radians(float(prior_sigma[1]))
    area = tuple(args.area) if args.area else default_area(world)
    assert len(area) == 4
    area4 = (float(area[0]), float(area[1]), float(area[2]), float(area[3]))
    view = bench.view
    t_start = time.perf_counter()

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.calibration_out) if args.calibration_out else Path(tmp) / "vlp_calibration.toml"
        report = calibrate(bench, area4, out)
        calibrated = VlpPipeline(view.intrinsics, view.led_map, view.mount, calibration=report.calibration)
        uncalibrated = VlpPipeline(view.intrinsics, view.led_map, view.mount)
        cal_tally, uncal_tally = bench.tally(), bench.tally()
        if args.speed > 0:
            cal_tally = driving(bench, calibrated, area4, args.points, args.speed)
            bench.rng = np.random.default_rng(args.seed + 1)
            uncal_tally = driving(bench, uncalibrated, area4, args.points, args.speed)
            disp_cal = disp_uncal = {"offset_cm": math.nan, "radius_cm": math.nan}
        else:
            for _ in range(args.points):
                pose = bench.random_pose(area4)
                static_frames(bench, pose, args.repeats, [uncalibrated, calibrated], [uncal_tally, cal_tally])
            centre = Pose2D(0.5 * (area4[0] + area4[2]), 0.5 * (area4[1] + area4[3]), 0.0)
            disp_cal = dispersion(bench, calibrated, centre)
            disp_uncal = dispersion(bench, uncalibrated, centre)

    cal = report.calibration
    true_intr = bench.renderer.output_intrinsics
    tracks_ok = sum(1 for truth_id, got in cal_tally.tracks_final.values() if got == truth_id)
    summary: dict[str, Any] = {
        "world": world.name,
        "mode": "driving" if args.speed > 0 else "static",
        "speed_mps": args.speed,
        "points": args.points,
        "repeats": args.repeats if args.speed == 0 else None,
        "frames": len(cal_tally.latency_ms),
        "fixes": len(cal_tally.errors_m),
        "degraded_fixes": len(cal_tally.degraded_errors_m),
        "degraded_mean_error_cm": _summary_errors(cal_tally.degraded_errors_m)["mean_error_cm"],
        "degraded_max_error_cm": _summary_errors(cal_tally.degraded_errors_m)["max_error_cm"],
        "fix_fraction": _ratio(
            len(cal_tally.errors_m) + len(cal_tally.degraded_errors_m), len(cal_tally.latency_ms)
        ),
        "unflagged_over_5cm": cal_tally.unflagged_over_5cm,
        "protection_coverage": _ratio(cal_tally.protected, len(cal_tally.errors_m)),
        "frame_ms_max": max(cal_tally.latency_ms, default=math.nan),
        "frame_cpu_ms_max": max(cal_tally.cpu_ms, default=math.nan),
        "flags": dict(cal_tally.flags),
        "no_fix": dict(cal_tally.no_fix),
        **_summary_errors(cal_tally.errors_m),
        "uncalibrated_mean_error_cm": _summary_errors(uncal_tally.errors_m)["mean_error_cm"],
        "uncalibrated_median_error_cm": _summary_errors(uncal_tally.errors_m)["median_error_cm"],
        "uncalibrated_p90_error_cm": _summary_errors(uncal_tally.errors_m)["p90_error_cm"],
        "uncalibrated_max_error_cm": _summary_errors(uncal_tally.errors_m)["max_error_cm"],
        "id_accuracy_frame": _ratio(cal_tally.ids_frame_ok, cal_tally.ids_decoded),
        "id_accuracy_track": _ratio(cal_tally.ids_track_ok, cal_tally.ids_settled),
        "id_unsettled_fraction": _ratio(cal_tally.ids_seen - cal_tally.ids_settled, cal_tally.ids_seen),
        "id_tracks_correct": f"{tracks_ok}/{len(cal_tally.tracks_final)}",
        "id_observations": cal_tally.ids_seen,
        "id_frames_decoded": cal_tally.ids_decoded,
        "id_frame_wrong": _ratio(cal_tally.ids_named_wrong, cal_tally.ids_named),
        "decode_refusals": dict(cal_tally.refusals),
        "association_accuracy": _ratio(cal_tally.assoc_ok, cal_tally.assoc_seen),
        "dispersion_offset_cm": disp_cal["offset_cm"],
        "dispersion_radius_cm": disp_cal["radius_cm"],
        "uncalibrated_dispersion_offset_cm": disp_uncal["offset_cm"],
        "uncalibrated_dispersion_radius_cm": disp_uncal["radius_cm"],
        "latency_ms_median": _pct(cal_tally.latency_ms, 50),
        "latency_ms_p99": _pct(cal_tally.latency_ms, 99),
        "latency_ms_stages_median": _stage_medians(cal_tally),
        "image_size_px": [view.intrinsics.width_px, view.intrinsics.height_px],
        "t_row_s": view.intrinsics.t_row_s,
        "true_t_row_s": world.camera.t_row_s,
        "calibration": {
            "file": report.file if args.calibration_out else None,
            "turn_frames": report.turn_frames,
            "tracks_used": report.tracks_used,
            "known_point_fixes": report.known_fixes,
            "principal_point_px": list(cal.principal_point_px) if cal.principal_point_px else None,
            "mount_tilt_deg": [math.degrees(a) for a in cal.mount_tilt_rad] if cal.mount_tilt_rad else None,
            "true_mount_tilt_deg": [math.degrees(a) for a in world.errors.camera_tilt_rad],
            "nominal_principal_point_px": [view.intrinsics.cx_px, view.intrinsics.cy_px],
            "true_principal_point_px": [true_intr.cx_px, true_intr.cy_px],
            "residual_rms_before_cm": 100.0 * cal.residual.rms_before_m if cal.residual else None,
            "residual_rms_after_cm": 100.0 * cal.residual.rms_after_m if cal.residual else None,
            "residual_refused": report.residual_refused,
            "rotation_centre_refused": report.rotation_centre_refused,
        },
        "prior": (
            f"odometry-grade on each run's first frame (sigma {bench.prior_sigma_xy_m} m, "
            f"{math.degrees(bench.prior_sigma_yaw_rad):.0f} deg, stated twice that): the map repeats ids"
            if bench.repeats_ids
            else None
        ),
        "area_m": list(area4),
        "seed": args.seed,
        "wall_time_s": time.perf_counter() - t_start,
    }
    return summary, cal_tally, uncal_tally, world


# -- the figure ----------------------------------------------------------------------------------------------
def draw_figure(
    path: Path, world: World, area: Sequence[float], cal: Tally, uncal: Tally, summary: dict[str, Any]
) -> None:
    """Estimated vs true positions (left) and the error CDFs (right), like the paper's Fig. 9."""
    if not cv2.imwrite(str(path), figure_image(world, area, cal, uncal, summary)):
        raise ConfigError("--png", f"could not write {path}")


def figure_image(
    world: World, area: Sequence[float], cal: Tally, uncal: Tally, summary: dict[str, Any]
) -> npt.NDArray[np.uint8]:
    """:func:`draw_figure`'s picture: both panels with ticks in metres / centimetres, legends, LED ids."""
    w, h = 1440, 840
    img = np.full((h, w, 3), 255, dtype=np.uint8)
    top, size = 110, 540
    # Left panel: positions.
    x0, y0, x1, y1 = area
    pad = 0.1 * max(x1 - x0, y1 - y0)
    left = 90
    axes = figure.Axes.fit((x0 - pad, x1 + pad, y0 - pad, y1 + pad), (left, top, left + size, top + size))
    bx0, bx1, by0, by1 = axes.bounds
    cv2.rectangle(img, (left, top), (left + size, top + size), figure.WHITE, -1)
    for led in world.leds:
        if bx0 <= led.x_m <= bx1 and by0 <= led.y_m <= by1:
            centre = axes.to_px(led.x_m, led.y_m)
            radius = max(round(led.diameter_m / 2 * axes.px_per_unit), 5)
            cv2.circle(img, centre, radius, figure.LED, -1, cv2.LINE_AA)
            figure.text(img, f"LED {led.id}", (centre[0] - 24, centre[1] + radius + 16), 0.45)
    # The truth underneath, the fixes on top: a fix within a millimetre still shows on its cross.
    for tx, ty in {(round(f[2], 4), round(f[3], 4)) for f in cal.fixes}:
        cv2.drawMarker(img, axes.to_px(tx, ty), figure.TRUTH, cv2.MARKER_CROSS, 18, 2)
    for ex, ey, _, _ in uncal.fixes:
        cv2.circle(img, axes.to_px(ex, ey), 3, figure.UNCALIBRATED, -1, cv2.LINE_AA)
    for ex, ey, _, _ in cal.fixes:
        cv2.circle(img, axes.to_px(ex, ey), 3, figure.VLP_FIX, -1, cv2.LINE_AA)
    axes.draw(img, grid=True)
    figure.title(img, f"vlp-agent eval vlp: VLP positioning on {world.name}", (20, 36))
    figure.text(img, "(a) VLP fixes vs true positions", (left, 76), 0.6)
    figure.legend(
        img,
        [
            figure.Entry("true position", figure.TRUTH, figure.Mark.CROSS),
            figure.Entry("VLP fix, calibrated", figure.VLP_FIX, figure.Mark.DOT),
            figure.Entry("VLP fix, uncalibrated", figure.UNCALIBRATED, figure.Mark.DOT),
            figure.Entry("LED (with its id)", figure.LED, figure.Mark.DOT),
        ],
        (left, top + size + 60),
    )
    figure.scale_bar(img, axes.px_per_unit, (left + size - 140, top + size + 110), target_px=140)
    # Right panel: CDFs.
    left2 = 820
    errs = [100.0 * e for e in cal.errors_m] + [100.0 * e for e in uncal.errors_m]
    e_max = max(max(errs) if errs else 1.0, 0.5) * 1.05
    cdf = figure.Axes((left2, top, left2 + size, top + size), (0.0, e_max, 0.0, 1.0))
    cdf.draw(img, "position error (cm)", "fraction of fixes", grid=True)
    p90 = cdf.to_px(0.0, 0.9)[1]
    cv2.line(img, (left2, p90), (left2 + size, p90), figure.GREY, 1)
    figure.text(img, "90 % of fixes", (left2 + size // 2 - 40, p90 - 6), 0.45, figure.GREY)
    for values, colour in ((uncal.errors_m, figure.UNCALIBRATED), (cal.errors_m, figure.VLP_FIX)):
        cm = np.sort(np.array(values) * 100.0)
        if cm.size == 0:
            continue
        xy = np.stack([cm, np.arange(1, cm.size + 1) / cm.size], axis=1)
        figure.draw_path(img, cdf, xy, colour, 3, start=False)
    figure.text(img, "(b) CDF of the position errors", (left2, 76), 0.6, figure.BLACK, 1)
    figure.legend(
        img,
        [
            figure.Entry("calibrated", figure.VLP_FIX),
            figure.Entry("uncalibrated", figure.UNCALIBRATED),
        ],
        (left2, top + size + 60),
    )
    figure.text(
        img,
        f"calibrated: mean {summary['mean_error_cm']:.2f} cm, p90 {summary['p90_error_cm']:.2f} cm; "
        f"uncalibrated: mean {summary['uncalibrated_mean_error_cm']:.2f} cm",
        (left2, top + size + 150),
        0.5,
    )
    return img


def _table(summary: dict[str, Any]) -> str:
    def f(v: Any, unit: str = "") -> str:
        if isinstance(v, float):
            return f"{v:.3f}{unit}" if math.isfinite(v) else "n/a"
        return f"{v}{unit}"

    cal = summary["calibration"]
    stages = summary["latency_ms_stages_median"]
    rows = [
        (
            "world",
            f"{summary['world']} ({summary['mode']}"
            + (f", {summary['speed_mps']} m/s)" if summary["mode"] == "driving" else ")"),
        ),
        (
            "frames / fixes",
            f"{summary['frames']} / {summary['fixes']} ({summary['degraded_fixes']} degraded)",
        ),
        ("no fix", ", ".join(f"{k}: {v}" for k, v in summary["no_fix"].items()) or "none"),
        (
            "fix fraction / unflagged > 5 cm",
            f"{f(summary['fix_fraction'])} / {summary['unflagged_over_5cm']}",
        ),
        ("protection coverage", f(summary["protection_coverage"])),
        (
            "error mean / median",
            f"{f(summary['mean_error_cm'], ' cm')} / {f(summary['median_error_cm'], ' cm')}",
        ),
        ("error p90 / max", f"{f(summary['p90_error_cm'], ' cm')} / {f(summary['max_error_cm'], ' cm')}"),
        (
            "uncalibrated mean / p90",
            f"{f(summary['uncalibrated_mean_error_cm'], ' cm')} / "
            f"{f(summary['uncalibrated_p90_error_cm'], ' cm')}",
        ),
        (
            "dispersion offset / radius",
            f"{f(summary['dispersion_offset_cm'], ' cm')} / {f(summary['dispersion_radius_cm'], ' cm')}",
        ),
        (
            "  uncalibrated",
            f"{f(summary['uncalibrated_dispersion_offset_cm'], ' cm')} / "
            f"{f(summary['uncalibrated_dispersion_radius_cm'], ' cm')}",
        ),
        (
            "id accuracy frame / track",
            f"{f(summary['id_accuracy_frame'])} / {f(summary['id_accuracy_track'])} "
            f"({summary['id_observations']} LED sightings, tracks {summary['id_tracks_correct']})",
        ),
        (
            "latency median / p99",
            f"{f(summary['latency_ms_median'], ' ms')} / {f(summary['latency_ms_p99'], ' ms')} "
            f"(max {f(summary['frame_ms_max'], ' ms')})",
        ),
        ("  per stage (median)", ", ".join(f"{k} {v:.3f}" for k, v in stages.items())),
        (
            "principal point",
            f"{cal['principal_point_px']} (nominal {cal['nominal_principal_point_px']}, "
            f"true {cal['true_principal_point_px']})",
        ),
    ]
    for key, what in (("rotation_centre_refused", "no rotation centre"), ("residual_refused", "no residual")):
        if cal[key]:
            rows.append((what, str(cal[key])))
    width = max(len(r[0]) for r in rows)
    return "\n".join(f"{name.ljust(width)}  {value}" for name, value in rows)


def run(args: argparse.Namespace) -> int:
    summary, cal, uncal, world = evaluate(args)
    if args.json:
        print(dumps_json(summary))
        return 0
    print(_table(summary))
    png = Path(args.png) if args.png else Path(f"vlp_eval_{world.name}.png")
    draw_figure(png, world, summary["area_m"], cal, uncal, summary)
    print(f"figure: {png}")
    return 0
