"""Step ``vlp-error``: the VLP error calibration of ``reference/vlp.md`` §1.6, with the VLP pipeline's own
procedures (``agent.vlp.calibration``, file format in docs/vlp.md).

1. **Rotation centre.** The robot turns a full turn in place under two or more LEDs while the pipeline tracks
   them; every LED's image centre draws a circle about the image of the vertical through the lens, and
   ``fit_rotation_centre`` turns the circles into the principal point that makes the level-camera model right
   (it absorbs the principal-point error and the camera's tilt together).
2. **Residual correction.** At known points (``--points`` CSV of x_m,y_m, or typed; on the simulated robot a
   3 x 3 grid over the LED area) the robot stands at ``--headings`` headings and the pipeline, with the new
   centre, takes fixes; ``fit_residual_correction`` fits the field of their errors (fix - truth).
3. **Before and after.** The errors at the known points without any calibration and with it; on the simulated
   robot also at ``--test-points`` fresh random places (frames from the true world, never used to calibrate).

The robot is placed at each point by the user (who types nothing more: the point is where the mark is); on the
simulated robot it drives there by odometry and the "tape measure" is the simulation's truth.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from agent.vlp.calibration import (
    ResidualCorrection,
    RotationCentre,
    VlpCalibration,
    fit_rotation_centre,
    format_calibration,
    mount_tilt_from_shift,
    validated_residual_correction,
)
from agent.vlp.model import LedMap, VlpFix, VlpResult
from agent.vlp.pipeline import VlpPipeline
from calibration import plot
from calibration.context import StepContext
from calibration.report import (
    CalibrationError,
    Check,
    Console,
    Output,
    StepResult,
    ask_float,
    ask_int,
    ask_line,
)
from calibration.rig import Rig
from calibration.vlp_view import VlpView, view_for
from calibration.wheels import drive, go_to
from drivers.camera.base import Camera
from drivers.errors import DeviceError

__all__ = ["add_arguments", "interactive", "run"]

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

NAME = "vlp-error"
DEFAULT_FILE = "vlp.toml"
MAX_CENTRE_SIGMA_PX = 0.5
MIN_FIXES = 6
MAX_MEAN_ERROR_CM = 1.0
TURN_AT = 0.3


class FrameLoop:
    """Frames from the camera, handed to ``on_frame`` on a thread of their own while the robot moves."""

    def __init__(self, camera: Camera, on_frame: Callable[[Any, float], None]) -> None:
        self.camera = camera
        self.on_frame = on_frame
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="calibrate-frames", daemon=True)
        self.error: BaseException | None = None
        self.frames = 0

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                try:
                    frame = self.camera.grab(timeout_s=0.5)
                except DeviceError as exc:
                    log.warning("camera: %s", exc)
                    continue
                self.on_frame(frame.image, frame.host_time_ns * 1e-9)
                self.frames += 1
        except BaseException as exc:  # handed to the main thread by stop()
            self.error = exc

    def __enter__(self) -> FrameLoop:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        if self.error is not None and exc[0] is None:
            raise CalibrationError(f"processing frames failed: {self.error}") from self.error


@dataclass
class Tracks:
    """LED image tracks over a turn in place, and each track's LED height above the lens."""

    paths: dict[int, list[tuple[float, float]]] = field(default_factory=dict)
    heights: dict[int, float] = field(default_factory=dict)
    fixes: list[tuple[float, float]] = field(default_factory=list)
    frames: int = 0  # frames processed during the turn (a starved computer drops some)

    def add(self, result: VlpResult, led_map: LedMap, lens_height_m: float) -> None:
        for obs in result.leds:
            if obs.visibility != "full":
                continue
            self.paths.setdefault(obs.track_id, []).append(obs.centre_px)
            if obs.map_index is not None:
                self.heights[obs.track_id] = led_map.leds[obs.map_index].z_m - lens_height_m
        if isinstance(result, VlpFix) and not result.degraded:
            self.fixes.append((result.x_m, result.y_m))


@dataclass
class Stop:
    """Fixes taken at one known point and heading: without calibration, and with the rotation centre."""

    truth: tuple[float, float]
    raw: list[tuple[float, float]] = field(default_factory=list)
    centred: list[tuple[float, float]] = field(default_factory=list)


def read_points(path: Path) -> list[tuple[float, float]]:
    try:
        rows = list(csv.reader(path.read_text(encoding="utf-8").splitlines()))
    except OSError as exc:
        raise CalibrationError(f"cannot read {path}: {exc.strerror or exc}") from exc
    if not rows or [h.strip() for h in rows[0]][:2] != ["x_m", "y_m"]:
        raise CalibrationError(f"{path} line 1: the header must be x_m,y_m")
    points = []
    for line_no, row in enumerate(rows[1:], start=2):
        if not row or not "".join(row).strip():
            continue
        try:
            x, y = float(row[0]), float(row[1])
        except (ValueError, IndexError):
            raise CalibrationError(
                f"{path.name} line {line_no}: {','.join(row)!r} is not two numbers"
            ) from None
        points.append((x, y))
    if len(points) < 3:
        raise CalibrationError(f"{path} holds {len(points)} points; at least 3 are needed")
    return points


def grid_points(led_map: LedMap, n: int = 3) -> list[tuple[float, float]]:
    """``n`` x ``n`` points over the inner part of the LEDs' bounding box (cell centres)."""
    xy = led_map.xyz_m[:, :2]
    (x0, y0), (x1, y1) = xy.min(axis=0), xy.max(axis=0)
    return [
        (x0 + (i + 0.5) / n * (x1 - x0), y0 + (j + 0.5) / n * (y1 - y0)) for j in range(n) for i in range(n)
    ]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--points", metavar="CSV", help="known points: x_m,y_m (default on --sim: a 3 x 3 grid)")
    p.add_argument("--headings", type=int, default=2, help="headings at each point (default 2)")
    p.add_argument("--frames", type=int, default=4, help="frames at each stop (default 4)")
    p.add_argument(
        "--turn-radps", type=float, default=0.6, help="turning rate of the full turn (default 0.6)"
    )
    p.add_argument("--degree", type=int, default=1, help="degree of the residual correction (default 1)")
    p.add_argument(
        "--camera-info", metavar="FILE", help="camera calibration (default: the config's; --sim: nominal)"
    )
    p.add_argument(
        "--led-map", metavar="FILE", help="LED map (default: the config's; --sim: the surveyed one)"
    )
    p.add_argument(
        "--test-points", type=int, default=12, help="--sim: fresh places to score before and after"
    )


def interactive(ctx: StepContext, options: argparse.Namespace) -> argparse.Namespace:
    if ctx.sim is None:
        answer = ask_line(
            ctx.console, "known points from a CSV file (x_m,y_m), or Enter to type them: "
        ).strip()
        options.points = answer or None
    return options


def _type_points(console: Console) -> list[tuple[float, float]]:
    n = ask_int(
        console, "how many known points (marks on the floor under the LEDs)", 5, minimum=3, maximum=50
    )
    return [
        (
            ask_float(console, f"point {k} x_m", None, minimum=-1e4, maximum=1e4),
            ask_float(console, f"point {k} y_m", None, minimum=-1e4, maximum=1e4),
        )
        for k in range(1, n + 1)
    ]


def run(ctx: StepContext, options: argparse.Namespace) -> StepResult:
    console = ctx.console
    ctx.require_robot("the VLP error calibration")
    output = ctx.output(options.output, DEFAULT_FILE)
    if options.headings < 1 or options.frames < 1:
        raise CalibrationError("--headings and --frames must be at least 1")
    view = view_for(ctx, camera_info=options.camera_info, led_map=options.led_map)
    if view.led_map is None:
        raise CalibrationError(
            "no LED map: run `vlp-agent calibrate leds` and pass --led-map, or set [vlp] led_map"
        )
    led_map = view.led_map
    points = read_points(Path(options.points)) if options.points else None
    if points is None:
        points = grid_points(led_map) if ctx.sim is not None else _type_points(console)
    console.say(f"vlp-error: {view.source}; {len(points)} known points x {options.headings} headings")
    uncal = VlpPipeline(view.intrinsics, led_map, view.mount)
    size = (view.intrinsics.width_px, view.intrinsics.height_px)
    with Rig.for_context(ctx) as rig:
        camera = rig.camera()
        servos = rig.servos()
        servos.torque(True)
        r0, b0 = rig.nominal.wheel_radius_m, rig.nominal.track_m
        sim = rig.simulation
        pose: tuple[float, float, float] | None = None
        if sim is not None:
            s = sim.world.robot.start
            # Off the LEDs' middle (TURN_AT of the way in from the south-west corner of their box), so that
            # they are at different distances from the axis: the circles' radii then tell the tilt apart.
            (x0, y0), (x1, y1) = led_map.xyz_m[:, :2].min(axis=0), led_map.xyz_m[:, :2].max(axis=0)
            centre = (x0 + TURN_AT * (x1 - x0), y0 + TURN_AT * (y1 - y0))
            pose = go_to(
                servos,
                (s.x_m, s.y_m, s.yaw_rad),
                (float(centre[0]), float(centre[1])),
                radius_m=r0,
                track_m=b0,
                speed_mps=0.25,
                turn_radps=1.5,
                status=console.status,
            )
        else:
            ask_line(
                console,
                "  put the robot under three or more LEDs, nearer one than the others (their distances tell "
                "the camera's tilt), with room to turn, then press Enter ",
            )

        # 1. Rotation centre.
        tracks = Tracks()

        def on_turn_frame(image: Any, t: float) -> None:
            tracks.add(uncal.process(image, t), led_map, view.mount.z_m)

        console.say("  turning a full turn in place")
        with FrameLoop(camera, on_turn_frame) as loop:
            drive(
                servos,
                radius_m=r0,
                track_m=b0,
                angle_rad=2.0 * math.pi,
                speed_mps=0.1,
                turn_radps=options.turn_radps,
                tick=lambda: None,
                status=console.status,
            )
        tracks.frames = loop.frames
        if pose is not None:
            pose = (pose[0], pose[1], pose[2] + 2.0 * math.pi)
        usable = [k for k in tracks.paths if k in tracks.heights]
        rc = fit_rotation_centre(
            [np.array(tracks.paths[k]) for k in usable],
            [tracks.heights[k] for k in usable],
            view.intrinsics,
            view.mount,
        )
        if isinstance(rc, str):
            # The turn saw too little (a sparse ceiling): the fixes at the known points still give the
            # residual correction, with the camera's own principal point.
            rc = f"{rc} ({loop.frames} frames, {len(usable)} LED tracks)"
            centred_cal = VlpCalibration(size)
            console.say(f"  no rotation centre, the camera's principal point is kept: {rc}")
        else:
            tilt = mount_tilt_from_shift(rc.tilt_px, view.intrinsics) if rc.tilt_px is not None else None
            centred_cal = VlpCalibration(size, (rc.cx_px, rc.cy_px), rc.sigma_px, mount_tilt_rad=tilt)
            console.say(
                f"  rotation centre ({rc.cx_px:.2f}, {rc.cy_px:.2f}) px from {len(rc.circles)} LED circles; "
                f"the camera's was ({view.intrinsics.cx_px:.2f}, {view.intrinsics.cy_px:.2f})"
                + (
                    f"; camera tilt on its mount {math.degrees(tilt[0]):.2f} / "
                    f"{math.degrees(tilt[1]):.2f} deg (roll / pitch)"
                    if tilt is not None
                    else ""
                )
            )
        centred = VlpPipeline(view.intrinsics, led_map, view.mount, calibration=centred_cal)

        # 2. Fixes at known points.
        stops: list[Stop] = []
        for n, point in enumerate(points, start=1):
            for h in range(options.headings):
                heading = h * 2.0 * math.pi / options.headings
                if pose is not None:
                    pose = go_to(
                        servos,
                        pose,
                        point,
                        radius_m=r0,
                        track_m=b0,
                        heading_rad=heading,
                        speed_mps=0.25,
                        turn_radps=1.5,
                        status=console.status,
                    )
                elif h == 0:
                    ask_line(
                        console,
                        f"  put the robot on point {n} ({point[0]:.3f}, {point[1]:.3f}), then press Enter ",
                    )
                else:
                    ask_line(
                        console,
                        f"  turn the robot about {360 // options.headings} degrees on the point, then press "
                        "Enter ",
                    )
                truth = point
                if sim is not None:
                    # The tape measure: where the robot really stands.
                    p = sim.pose()
                    truth = (round(p.x_m, 3), round(p.y_m, 3))
                stop = Stop(truth)
                uncal.reset()
                centred.reset()
                for _ in range(options.frames):
                    frame = camera.grab(timeout_s=2.0)
                    t = frame.host_time_ns * 1e-9
                    for pipe, out in ((uncal, stop.raw), (centred, stop.centred)):
                        result = pipe.process(frame.image, t)
                        if isinstance(result, VlpFix) and not result.degraded:
                            out.append((result.x_m, result.y_m))
                stops.append(stop)
                console.status(
                    f"  point {n}/{len(points)}, heading {h + 1}/{options.headings}: {len(stop.centred)} "
                    "fixes"
                )
        console.status("")
    est = np.array([f for s in stops for f in s.centred]).reshape(-1, 2)
    true = np.array([s.truth for s in stops for _ in s.centred]).reshape(-1, 2)
    n_coef = (options.degree + 1) * (options.degree + 2) // 2
    if len(est) < max(MIN_FIXES, n_coef):
        raise CalibrationError(
            f"only {len(est)} fixes at the known points (at least {max(MIN_FIXES, n_coef)} needed): "
            "are two LEDs in view at every point?"
        )
    checked = validated_residual_correction(est, true, degree=options.degree)
    residual = checked if isinstance(checked, ResidualCorrection) else None
    if isinstance(checked, str):
        console.say(f"  no residual correction: {checked}")
    calibration = dataclasses.replace(centred_cal, residual=residual)
    evaluation = _evaluate(ctx, view, calibration, options.test_points) if ctx.sim is not None else None
    refused = checked if isinstance(checked, str) else None
    return _result(calibration, rc, stops, residual, refused, tracks, evaluation, view, output, points)


def _standing(pose: Any) -> Callable[[float], Any]:
    """The pose of a robot standing still, at any time."""
    return lambda t: pose


def _errors_cm(pairs: list[tuple[tuple[float, float], tuple[float, float]]]) -> list[float]:
    return [100.0 * math.hypot(f[0] - t[0], f[1] - t[1]) for f, t in pairs]


def _evaluate(
    ctx: StepContext, view: VlpView, calibration: VlpCalibration, count: int
) -> dict[str, Any] | None:
    """Simulated robot only: fixes before and after at ``count`` fresh random places (three frames each),
    frames rendered from the true world; none of them was used to calibrate."""
    from drivers.sim.render import RollingShutterRenderer
    from drivers.sim.world import Pose2D

    if count <= 0 or ctx.sim is None or view.led_map is None:
        return None
    world = ctx.sim.load()
    renderer = RollingShutterRenderer.for_world(world, seed=ctx.sim.seed + 7)
    rng = np.random.default_rng(ctx.sim.seed + 11)
    xy = view.led_map.xyz_m[:, :2]
    (x0, y0), (x1, y1) = xy.min(axis=0), xy.max(axis=0)
    before = VlpPipeline(view.intrinsics, view.led_map, view.mount)
    after = VlpPipeline(view.intrinsics, view.led_map, view.mount, calibration=calibration)
    errors: dict[str, list[float]] = {"before": [], "after": []}
    clock = 5000.0
    done = 0
    for _ in range(50 * count):
        if done >= count:
            break
        pose = Pose2D(
            float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1)), float(rng.uniform(-math.pi, math.pi))
        )
        probe = renderer.render(_standing(pose), clock)
        if sum(1 for led in probe.truth.leds if led.in_image) < 2:
            continue
        before.reset()
        after.reset()
        for _ in range(3):
            clock += 1.0 / world.camera.frame_rate_hz
            frame = renderer.render(_standing(pose), clock + float(rng.uniform(0.0, 1e-3)))
            for name, pipe in (("before", before), ("after", after)):
                result = pipe.process(frame.image, frame.truth.t_mid_s)
                if isinstance(result, VlpFix) and not result.degraded:
                    errors[name].append(100.0 * math.hypot(result.x_m - pose.x_m, result.y_m - pose.y_m))
        clock += 10.0
        done += 1
    return {
        "test_points": done,
        "mean_error_cm_before": round(float(np.mean(errors["before"])), 4) if errors["before"] else None,
        "mean_error_cm_after": round(float(np.mean(errors["after"])), 4) if errors["after"] else None,
        "max_error_cm_after": round(float(np.max(errors["after"])), 4) if errors["after"] else None,
        "fixes_after": len(errors["after"]),
    }


def _corrected(residual: ResidualCorrection | None, fix: tuple[float, float]) -> tuple[float, float]:
    return residual.apply(*fix) if residual is not None else fix


def _result(
    calibration: VlpCalibration,
    rc: RotationCentre | str,
    stops: list[Stop],
    residual: ResidualCorrection | None,
    residual_refused: str | None,
    tracks: Tracks,
    evaluation: dict[str, Any] | None,
    view: VlpView,
    output: Path,
    points: list[tuple[float, float]],
) -> StepResult:
    raw_pairs = [(f, s.truth) for s in stops for f in s.raw]
    cal_pairs = [(_corrected(residual, f), s.truth) for s in stops for f in s.centred]
    before, after = _errors_cm(raw_pairs), _errors_cm(cal_pairs)
    mean_before = float(np.mean(before)) if before else math.nan
    mean_after = float(np.mean(after)) if after else math.nan
    centre = rc if isinstance(rc, RotationCentre) else None
    circles = len(centre.circles) if centre is not None else 0
    checks = [
        Check("rotation centre: LED circles used", float(circles), 1.0, "", at_least=True),
        Check(
            "rotation centre: spread of the circle centres",
            centre.sigma_px if centre is not None else math.nan,
            MAX_CENTRE_SIGMA_PX,
            "px",
        ),
        Check("fixes at the known points", float(len(after)), float(MIN_FIXES), "", at_least=True),
        Check("mean error at the known points, after", mean_after, MAX_MEAN_ERROR_CM, "cm"),
    ]
    values: dict[str, Any] = {
        "principal_point_px": [round(centre.cx_px, 3), round(centre.cy_px, 3)] if centre else None,
        "principal_point_sigma_px": round(centre.sigma_px, 4) if centre else None,
        "rotation_centre_refused": rc if isinstance(rc, str) else None,
        "mount_tilt_deg": [round(math.degrees(a), 4) for a in calibration.mount_tilt_rad]
        if calibration.mount_tilt_rad
        else None,
        "nominal_principal_point_px": [round(view.intrinsics.cx_px, 3), round(view.intrinsics.cy_px, 3)],
        "circles": circles,
        "turn_frames": tracks.frames,
        "turn_tracks": len(tracks.paths),
        "known_point_fixes": len(after),
        "known_points_mean_error_cm_before": round(mean_before, 4),
        "known_points_mean_error_cm_after": round(mean_after, 4),
        "residual_rms_before_m": round(residual.rms_before_m, 6) if residual else None,
        "residual_rms_after_m": round(residual.rms_after_m, 6) if residual else None,
        "residual_refused": residual_refused,
    }
    report = [
        f"rotation centre ({centre.cx_px:.2f}, {centre.cy_px:.2f}) px (was ({view.intrinsics.cx_px:.2f}, "
        f"{view.intrinsics.cy_px:.2f})), spread {centre.sigma_px:.3f} px over {circles} LED circles"
        if centre is not None
        else f"no rotation centre (the camera's principal point is kept): {rc}",
        f"residual correction (degree {residual.degree}) from {residual.points} fixes at {len(points)} "
        "points: rms "
        f"{100 * residual.rms_before_m:.2f} -> {100 * residual.rms_after_m:.2f} cm"
        if residual is not None
        else f"no residual correction: {residual_refused}",
        f"at the known points: mean error {mean_before:.2f} cm before, {mean_after:.2f} cm after",
    ]
    if evaluation is not None:
        values["evaluation"] = evaluation
        values["mean_error_cm_before"] = evaluation["mean_error_cm_before"]
        values["mean_error_cm_after"] = evaluation["mean_error_cm_after"]
        if evaluation["mean_error_cm_after"] is not None:
            report.append(
                f"at {evaluation['test_points']} fresh places on the simulated robot: mean error "
                f"{evaluation['mean_error_cm_before']:.2f} cm before, "
                f"{evaluation['mean_error_cm_after']:.2f} cm after"
            )
    text = format_calibration(
        calibration,
        "vlp-agent calibrate vlp-error: "
        + (f"rotation centre from {circles} LED circles" if centre else f"no rotation centre: {rc}")
        + "; "
        + (
            f"residual from {residual.points} fixes at {len(points)} known points"
            if residual
            else f"no residual correction: {residual_refused}"
        ),
    )
    figure = _figure(stops, residual, centre, tracks, view, report, checks)
    advice = [f'set calibration = "{output}" in the [vlp] table of the robot config']
    if not all(c.ok for c in checks):
        advice.insert(
            0,
            "the calibration is weak: turn under more LEDs, check the LED map (vlp-agent calibrate leds) "
            "and the camera calibration, and place the robot carefully on the marks",
        )
    outputs = [Output(output, text), Output(output.with_suffix(".png"), plot.png(figure), report=True)]
    return StepResult(NAME, values, checks, report, advice, outputs)


def _figure(
    stops: list[Stop],
    residual: ResidualCorrection | None,
    rc: RotationCentre | None,
    tracks: Tracks,
    view: VlpView,
    report: list[str],
    checks: list[Check],
) -> Any:
    truth = np.array([s.truth for s in stops]).reshape(-1, 2)
    raw = np.array([f for s in stops for f in s.raw]).reshape(-1, 2)
    cal = np.array([_corrected(residual, f) for s in stops for f in s.centred]).reshape(-1, 2)
    fixes = plot.scatter(
        [
            plot.Series(truth, plot.TRUTH, "known point", 7),
            plot.Series(raw, plot.UNCALIBRATED, "fix before calibration", 2),
            plot.Series(cal, plot.VLP_FIX, "fix after calibration", 2),
        ],
        title="fixes at the known points",
        axis_labels=("x (m)", "y (m)"),
    )
    # Fix errors, magnified: each fix minus its point, in cm.
    err_before = np.array(
        [(100 * (f[0] - s.truth[0]), 100 * (f[1] - s.truth[1])) for s in stops for f in s.raw]
    ).reshape(-1, 2)
    err_after = np.array(
        [
            (100 * (a[0] - s.truth[0]), 100 * (a[1] - s.truth[1]))
            for s in stops
            for a in (_corrected(residual, f) for f in s.centred)
        ]
    ).reshape(-1, 2)
    errors = plot.scatter(
        [
            plot.Series(err_before, plot.UNCALIBRATED, "before calibration", 2),
            plot.Series(err_after, plot.VLP_FIX, "after calibration", 2),
        ],
        title="fix errors; the circle: 5 mm",
        axis_labels=("x error (cm)", "y error (cm)"),
        circles=[(0.0, 0.0, 0.5, plot.GREEN)],
    )
    circles = [
        plot.Series(np.array(p), plot.BLUE, "an LED's image over the turn" if k == 0 else "", 1)
        for k, p in enumerate(tracks.paths.values())
    ]
    centre = [plot.Series(np.array([[rc.cx_px, rc.cy_px]]), plot.RED, "rotation centre", 4)] if rc else []
    nominal = plot.Series(
        np.array([[view.intrinsics.cx_px, view.intrinsics.cy_px]]), plot.BLACK, "nominal", 4
    )
    turn = plot.scatter(
        [*circles, *centre, nominal],
        title="LED tracks over the turn",
        axis_labels=("u (px)", "v (px)"),
        bounds=(0.0, float(view.intrinsics.width_px), 0.0, float(view.intrinsics.height_px)),
        flip_y=True,
    )
    text = plot.text_panel(report + [c.describe() for c in checks], title="VLP error calibration")
    return plot.grid([turn, fixes, errors, text])
