"""Step ``mount``: the camera's tilt, and its yaw and position on the base.

* **Tilt from the IMU at rest** (the IMU fixed to the camera's bracket): gravity in the sensor frame,
  f = g (-sin p, sin r cos p, cos r cos p) for R = Rz(yaw) Ry(p) Rx(r), gives roll = atan2(f_y, f_z) and
  pitch = atan2(-f_x, hypot(f_y, f_z)). Measured at two headings 180 degrees apart and averaged, which takes
  out a sloping floor (fixed in the room) and keeps the mount's tilt (fixed on the robot). The accelerometer's
  own bias is not separable from the tilt: 0.03 m/s^2 of bias is 0.2 degrees.
* **Tilt from a level board** held above the camera: the board's normal, seen from the camera, is the
  vertical, n = (-sin p, sin r cos p, cos r cos p). Also averaged over the two headings, which cancels the
  board's own tilt (and tells how level it was).
* **Yaw on the base**: drive straight ahead (and back) under the board. In the camera's level frame the board
  moves by -d (cos psi, -sin psi), so psi = atan2(dy, -dx).
* **Position on the base** (lens off the turning axis): at turned headings theta_k (read from the board's own
  rotation) the board is at b_k = Rz(-theta_k) q - c in the level camera frame, linear in q (the board
  relative to the axis) and c (the lens relative to the axis); the lens sits at Rz(psi) c on the base.

The board pose comes from ``cv2.solvePnP`` with the camera calibration (``--camera-info``, by default the
intrinsics step's file in the output folder). With ``--sim`` the robot is built with the camera turned and off
its drawn place, the IMU on the camera bracket, and a board level 0.6 m above the lens.
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
import numpy.typing as npt

from calibration import plot
from calibration.boards import BoardDetector
from calibration.camera_info import CameraInfo, parse_camera_info
from calibration.context import StepContext
from calibration.intrinsics import DEFAULT_FILE as CAMERA_INFO_FILE
from calibration.intrinsics import add_board_arguments, board_spec
from calibration.report import CalibrationError, Check, Output, StepResult, ask_choice
from calibration.rig import Rig
from calibration.wheels import drive
from drivers.errors import ConfigError, DeviceError
from drivers.imu.base import Imu
from drivers.registry import DeviceKind
from drivers.sim.world import Mount

__all__ = [
    "BoardPose",
    "add_arguments",
    "fit_lens_offset",
    "interactive",
    "run",
    "tilt_from_gravity",
    "tilt_from_normal",
    "yaw_from_board_shift",
]

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
ImageU8 = npt.NDArray[np.uint8]

NAME = "mount"
DEFAULT_FILE = "mount.toml"
STANDARD_GRAVITY = 9.80665
TILT_AGREEMENT_DEG = 0.3
YAW_AGREEMENT_DEG = 0.5
OFFSET_RMS_M = 0.005
AT_REST_MPS2 = 0.15


# -- geometry (pure) -----------------------------------------------------------------------------------------
def tilt_from_normal(up: FloatArray) -> tuple[float, float]:
    """(roll, pitch) of the camera from the world's up direction in camera coordinates, R = Rz Ry(p) Rx(r)."""
    u = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    return math.atan2(float(u[1]), float(u[2])), math.atan2(
        -float(u[0]), math.hypot(float(u[1]), float(u[2]))
    )


def tilt_from_gravity(accel_mps2: FloatArray) -> tuple[float, float]:
    """(roll, pitch) from the accelerometer at rest: it reads the specific force, +g along the vertical."""
    return tilt_from_normal(accel_mps2)


def level_rotation(roll: float, pitch: float) -> FloatArray:
    """Ry(pitch) Rx(roll): camera coordinates -> the camera's level frame (turned only by its yaw)."""
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    out: FloatArray = ry @ rx
    return out


@dataclass(frozen=True, slots=True)
class BoardPose:
    """The board seen from the camera: p_camera = rotation p_board + translation; reprojection rms (px)."""

    rotation: FloatArray
    translation_m: FloatArray
    rms_px: float

    @property
    def up(self) -> FloatArray:
        """The board's normal pointing away from the camera (up, for a board above it)."""
        n: FloatArray = self.rotation[:, 2]
        return n if n[2] > 0 else -n

    def level(self, roll: float, pitch: float) -> tuple[FloatArray, float]:
        """The board's position and in-plane angle in the camera's level frame."""
        lv = level_rotation(roll, pitch)
        position = lv @ self.translation_m
        x_axis = lv @ self.rotation[:, 0]
        return position, math.atan2(float(x_axis[1]), float(x_axis[0]))


def yaw_from_board_shift(shift: FloatArray) -> float:
    """The camera's yaw on the base from the board's move (level camera frame) as the base drives ahead."""
    return math.atan2(float(shift[1]), -float(shift[0]))


def fit_lens_offset(positions: list[FloatArray], turns_rad: list[float]) -> tuple[FloatArray, float]:
    """c (the lens relative to the turning axis, level camera frame at the first heading) from board positions
    b_k = Rz(-theta_k) q - c: least squares in (q, c). Returns (c, rms m)."""
    rows, rhs = [], []
    for b, theta in zip(positions, turns_rad, strict=True):
        cz, sz = math.cos(-theta), math.sin(-theta)
        rows.append(np.array([[cz, -sz, -1.0, 0.0], [sz, cz, 0.0, -1.0]]))
        rhs.append(np.asarray(b, dtype=np.float64)[:2])
    a, y = np.vstack(rows), np.concatenate(rhs)
    solution, *_ = np.linalg.lstsq(a, y, rcond=None)
    residual = a @ solution - y
    c: FloatArray = solution[2:]
    return c, float(np.sqrt(np.mean(residual**2)))


# -- seeing the board ----------------------------------------------------------------------------------------
class BoardCamera(Protocol):
    def grab(self) -> ImageU8: ...


class RealBoardCamera:
    def __init__(self, camera: Any) -> None:
        self.camera = camera

    def grab(self) -> ImageU8:
        image: ImageU8 = self.camera.grab(timeout_s=2.0).image
        return image


class SimBoardCamera:
    """The simulated camera looking at a level board fixed in the room, from wherever the robot is now."""

    def __init__(
        self, rig: Rig, world: Any, detector: BoardDetector, height_above_lens_m: float, seed: int
    ) -> None:
        from calibration.sim import target_renderer

        assert rig.simulation is not None
        self.sim = rig.simulation
        self.world = world
        self.renderer = target_renderer(world.camera, detector.target, seed=seed)
        mount = world.robot.camera_mount
        tilt = world.errors.camera_tilt_rad
        self.mount = mount
        self.tilt = level_rotation(mount.roll_rad + tilt[0], mount.pitch_rad + tilt[1])
        start = self.sim.pose()
        w, h = detector.target.size_m
        # Level, printed side down, turned 20 degrees in the room, centred over the lens at the start.
        beta = math.radians(20.0)
        self.r_world_board = np.array(
            [[math.cos(beta), -math.sin(beta), 0.0], [math.sin(beta), math.cos(beta), 0.0], [0.0, 0.0, 1.0]]
        )
        lens = self._lens(start)
        centre = np.array([lens[0], lens[1], mount.z_m + height_above_lens_m])
        self.origin = centre - self.r_world_board @ np.array([w / 2, h / 2, 0.0])

    def _lens(self, base: Any) -> FloatArray:
        c, s = math.cos(base.yaw_rad), math.sin(base.yaw_rad)
        m = self.mount
        return np.array([base.x_m + c * m.x_m - s * m.y_m, base.y_m + s * m.x_m + c * m.y_m, m.z_m])

    def grab(self) -> ImageU8:
        base = self.sim.pose()
        yaw = base.yaw_rad + self.mount.yaw_rad
        cz, sz = math.cos(yaw), math.sin(yaw)
        r_world_camera = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]]) @ self.tilt
        lens = self._lens(base)
        rotation = r_world_camera.T @ self.r_world_board
        translation = r_world_camera.T @ (self.origin - lens)
        return self.renderer.render(rotation, translation).image


def board_pose(camera: BoardCamera, detector: BoardDetector, info: CameraInfo, views: int = 3) -> BoardPose:
    """The board's pose, averaged over a few frames (the robot standing still)."""
    rotations, translations, errors = [], [], []
    for _ in range(views):
        detection = detector.detect(camera.grab())
        if detection is None:
            continue
        obj = detection.object_points.reshape(-1, 1, 3).astype(np.float64)
        img = detection.image_points.reshape(-1, 1, 2).astype(np.float64)
        ok, rvec, tvec = cv2.solvePnP(obj, img, info.k(), info.d(), flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            continue
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, info.k(), info.d(), rvec, tvec)
        proj, _ = cv2.projectPoints(obj, rvec, tvec, info.k(), info.d())
        errors.append(float(np.sqrt(np.mean(np.sum((proj - img) ** 2, axis=2)))))
        rot, _ = cv2.Rodrigues(rvec)
        rotations.append(rot)
        translations.append(tvec.reshape(3))
    if not rotations:
        raise CalibrationError(
            "the board is not in the picture: hold it level above the camera, all of it in view "
            f"({detector.spec.describe()})"
        )
    # Mean rotation: the average matrix projected back onto a rotation.
    u, _, vt = np.linalg.svd(np.mean(rotations, axis=0))
    rotation = u @ vt
    if np.linalg.det(rotation) < 0:
        u[:, -1] *= -1
        rotation = u @ vt
    return BoardPose(rotation, np.mean(translations, axis=0), float(np.mean(errors)))


_MIN_REST_SAMPLES = 10
_REST_PATIENCE = 4.0


def imu_at_rest(
    imu: Imu,
    seconds: float,
    status: Callable[[str], None],
    *,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> tuple[FloatArray, float]:
    """Mean specific force over ``seconds`` of fresh samples, and how much |f| varied (m/s^2). Reads are paced
    so each new sample is taken once (a part sampling at 100 Hz repeats its registers between samples).
    Fewer than ``_MIN_REST_SAMPLES`` by then (a slow bus, a busy computer): it reads on, up to
    ``_REST_PATIENCE`` times as long, before giving up. ``clock`` and ``sleep``: the time it reads by (a
    test's own clock, to pace a fake IMU without the wall clock)."""
    values: list[tuple[float, float, float]] = []
    start = clock()
    deadline, give_up = start + seconds, start + _REST_PATIENCE * seconds
    last: tuple[float, float, float] | None = None
    while (now := clock()) < deadline or (len(values) < _MIN_REST_SAMPLES and now < give_up):
        try:
            accel = imu.read().accel_mps2
        except DeviceError as exc:
            log.warning("IMU read failed: %s", exc)
            accel = None
        if accel is not None and accel != last:
            values.append(accel)
            last = accel
        status(f"  IMU at rest: {len(values)} samples")
        sleep(0.004)
    if len(values) < _MIN_REST_SAMPLES:
        raise CalibrationError(
            f"the IMU gave {len(values)} fresh samples in {clock() - start:.1f} s, fewer than "
            f"{_MIN_REST_SAMPLES}; check it (vlp-agent devices)"
        )
    a = np.array(values)
    return a.mean(axis=0), float(np.std(np.linalg.norm(a, axis=1)))


# -- the step ------------------------------------------------------------------------------------------------
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--method",
        choices=("imu", "target", "both"),
        default=None,
        help="tilt from the IMU at rest, a level board, or both (default: both when the robot has an IMU)",
    )
    p.add_argument(
        "--camera-info", metavar="FILE", help="camera calibration (default: camera_info.yaml in --dir)"
    )
    p.add_argument("--drive-m", type=float, default=0.2, help="drive under the board (default 0.2 m)")
    p.add_argument(
        "--imu-seconds", type=float, default=3.0, help="IMU averaging at each heading (default 3 s)"
    )
    p.add_argument(
        "--board-height-m", type=float, default=0.6, help="--sim: the board's height above the lens"
    )
    p.add_argument(
        "--exposure-ms", type=float, default=None, help="camera exposure while looking at the board"
    )
    add_board_arguments(p)


def interactive(ctx: StepContext, options: argparse.Namespace) -> argparse.Namespace:
    options.method = ask_choice(ctx.console, "tilt from", ["imu", "target", "both"], options.method or "both")
    return options


def _camera_info(ctx: StepContext, options: argparse.Namespace, world: Any) -> tuple[CameraInfo, str]:
    path = Path(options.camera_info) if options.camera_info else ctx.out_dir / CAMERA_INFO_FILE
    if path.is_file():
        try:
            return parse_camera_info(path.read_text(encoding="utf-8"), str(path)), str(path)
        except (OSError, ConfigError) as exc:
            raise CalibrationError(f"cannot use {path}: {exc}") from exc
    if options.camera_info:
        raise CalibrationError(f"no such camera_info file: {path}")
    if world is not None:
        from agent.sim_view import nominal_intrinsics

        intr = nominal_intrinsics(world)
        k = np.array([[intr.fx_px, 0, intr.cx_px], [0, intr.fy_px, intr.cy_px], [0, 0, 1.0]])
        return CameraInfo.from_matrices(
            intr.width_px, intr.height_px, k, np.array(intr.distortion)
        ), "the nominal camera"
    raise CalibrationError(
        f"no camera calibration: run `vlp-agent calibrate intrinsics` first (it writes {path}) or pass "
        "--camera-info"
    )


def run(ctx: StepContext, options: argparse.Namespace) -> StepResult:
    console = ctx.console
    ctx.require_robot("the mount calibration")
    output = ctx.output(options.output, DEFAULT_FILE)
    detector = BoardDetector(board_spec(options))
    truth: dict[str, float] | None = None
    world = None
    if ctx.sim is not None:
        from calibration.sim import as_built

        design = ctx.sim.load()
        world, _ = as_built(design, ctx.sim.seed)
        rig = Rig.simulated(world, ctx.sim.seed, design=design)
        m = world.robot.camera_mount
        tilt = world.errors.camera_tilt_rad
        truth = {
            "roll_rad": m.roll_rad + tilt[0],
            "pitch_rad": m.pitch_rad + tilt[1],
            "yaw_rad": m.yaw_rad,
            "x_m": m.x_m,
            "y_m": m.y_m,
        }
    else:
        rig = Rig.for_context(ctx)
    with rig:
        nominal = rig.nominal.camera_mount
        method = options.method or ("both" if rig.has(DeviceKind.IMU) else "target")
        info, info_source = _camera_info(ctx, options, ctx.sim.load() if ctx.sim is not None else None)
        console.say(f"mount: tilt from {method}; camera calibration from {info_source}")
        use_imu = method in ("imu", "both")
        use_target = method in ("target", "both")
        imu = rig.imu() if use_imu else None
        camera: BoardCamera | None = None
        if use_target:
            if ctx.sim is not None:
                camera = SimBoardCamera(rig, world, detector, options.board_height_m, ctx.sim.seed)
            else:
                exposure = None if options.exposure_ms is None else options.exposure_ms / 1000.0
                camera = RealBoardCamera(rig.camera(exposure_s=exposure))
                console.say(
                    "  hold the board level (use a spirit level) 0.5-1 m above the camera, printed side down"
                )
        servos = rig.servos()
        servos.torque(True)
        r0, b0 = rig.nominal.wheel_radius_m, rig.nominal.track_m

        def move(distance: float = 0.0, angle: float = 0.0) -> None:
            drive(
                servos,
                radius_m=r0,
                track_m=b0,
                distance_m=distance,
                angle_rad=angle,
                speed_mps=0.1,
                turn_radps=1.0,
                tick=lambda: None,
                status=console.status,
            )

        imu_tilts: list[tuple[float, float]] = []
        imu_noise: list[float] = []
        poses: list[BoardPose] = []
        shifts: list[BoardPose] = []
        for heading in (0, 1):
            if heading:
                console.say("  turning half a turn")
                move(angle=math.pi)
            if imu is not None:
                mean, spread = imu_at_rest(imu, options.imu_seconds, console.status)
                imu_tilts.append(tilt_from_gravity(mean))
                imu_noise.append(spread)
            if camera is not None:
                poses.append(board_pose(camera, detector, info))
        if camera is not None:
            console.say("  turning back, then driving ahead and back under the board")
            move(angle=-math.pi)
            poses.append(board_pose(camera, detector, info))
            move(distance=options.drive_m)
            shifts.append(board_pose(camera, detector, info))
            move(distance=-options.drive_m)
            shifts.append(board_pose(camera, detector, info))
        console.status("")
    return _result(imu_tilts, imu_noise, poses, shifts, nominal, truth, info_source, output)


def _mean_tilt(tilts: list[tuple[float, float]]) -> tuple[float, float]:
    return float(np.mean([t[0] for t in tilts])), float(np.mean([t[1] for t in tilts]))


def _result(
    imu_tilts: list[tuple[float, float]],
    imu_noise: list[float],
    poses: list[BoardPose],
    shifts: list[BoardPose],
    nominal: Mount,
    truth: dict[str, float] | None,
    info_source: str,
    output: Any,
) -> StepResult:
    checks: list[Check] = []
    report: list[str] = [f"camera calibration: {info_source}"]
    values: dict[str, Any] = {}
    roll, pitch = nominal.roll_rad, nominal.pitch_rad
    yaw, x_m, y_m = nominal.yaw_rad, nominal.x_m, nominal.y_m
    if imu_tilts:
        roll, pitch = _mean_tilt(imu_tilts)
        values["imu_tilt_deg"] = [round(math.degrees(roll), 4), round(math.degrees(pitch), 4)]
        slope = math.degrees(
            math.hypot(imu_tilts[0][0] - imu_tilts[1][0], imu_tilts[0][1] - imu_tilts[1][1]) / 2
        )
        report.append(
            f"IMU: roll {math.degrees(roll):+.3f} deg, pitch {math.degrees(pitch):+.3f} deg (floor slope "
            f"{slope:.2f} deg)"
        )
        checks.append(Check("IMU at rest: spread of |accel|", max(imu_noise), AT_REST_MPS2, "m/s^2"))
    if poses:
        target_tilts = [tilt_from_normal(p.up) for p in poses[:2]]
        t_roll, t_pitch = _mean_tilt(target_tilts)
        board_tilt = math.degrees(
            math.hypot(target_tilts[0][0] - target_tilts[1][0], target_tilts[0][1] - target_tilts[1][1]) / 2
        )
        values["target_tilt_deg"] = [round(math.degrees(t_roll), 4), round(math.degrees(t_pitch), 4)]
        values["board_tilt_deg"] = round(board_tilt, 3)
        report.append(
            f"board: roll {math.degrees(t_roll):+.3f} deg, pitch {math.degrees(t_pitch):+.3f} deg (the board "
            "was "
            f"{board_tilt:.2f} deg off level; reprojection {np.mean([p.rms_px for p in poses]):.2f} px)"
        )
        if imu_tilts:
            diff = math.degrees(math.hypot(roll - t_roll, pitch - t_pitch))
            checks.append(Check("tilt: IMU and board agree", diff, TILT_AGREEMENT_DEG, "deg"))
        else:
            roll, pitch = t_roll, t_pitch
        # Position and yaw use the board's tilt-free geometry, levelled with the tilt just found.
        lv = [p.level(roll, pitch) for p in poses]
        start_angle = lv[0][1]
        forward = [
            shifts[0].level(roll, pitch)[0] - lv[2][0],
            shifts[1].level(roll, pitch)[0] - shifts[0].level(roll, pitch)[0],
        ]
        yaws = [yaw_from_board_shift(forward[0]), yaw_from_board_shift(-forward[1])]
        yaw = float(np.mean(yaws))
        checks.append(
            Check(
                "yaw: drive ahead and back agree",
                math.degrees(abs(yaws[0] - yaws[1])),
                YAW_AGREEMENT_DEG,
                "deg",
            )
        )
        turns = [-math.remainder(angle - start_angle, math.tau) for _, angle in lv]
        c, rms = fit_lens_offset([position for position, _ in lv], turns)
        cz, sz = math.cos(yaw), math.sin(yaw)
        x_m, y_m = cz * c[0] - sz * c[1], sz * c[0] + cz * c[1]
        checks.append(Check("position: fit of the turns (rms)", rms, OFFSET_RMS_M, "m"))
        values.update(yaw_runs_deg=[round(math.degrees(v), 4) for v in yaws], offset_fit_rms_m=round(rms, 5))
        report.append(
            f"yaw on the base {math.degrees(yaw):+.3f} deg (drives "
            + ", ".join(f"{math.degrees(v):+.3f}" for v in yaws)
            + ")"
        )
        report.append(f"lens on the base x {1000 * x_m:+.1f} mm, y {1000 * y_m:+.1f} mm")
    values.update(
        roll_deg=round(math.degrees(roll), 4),
        pitch_deg=round(math.degrees(pitch), 4),
        yaw_deg=round(math.degrees(yaw), 4),
        x_m=round(x_m, 5),
        y_m=round(y_m, 5),
        z_m=nominal.z_m,
    )
    if truth is not None:
        values["tilt_error_deg"] = round(
            math.degrees(math.hypot(roll - truth["roll_rad"], pitch - truth["pitch_rad"])), 4
        )
        values["truth"] = {
            "roll_deg": math.degrees(truth["roll_rad"]),
            "pitch_deg": math.degrees(truth["pitch_rad"]),
            "yaw_deg": math.degrees(truth["yaw_rad"]),
            "x_m": truth["x_m"],
            "y_m": truth["y_m"],
        }
        line = f"against the simulated robot: tilt off by {values['tilt_error_deg']:.3f} deg"
        if poses:
            values["yaw_error_deg"] = round(
                abs(math.degrees(math.remainder(yaw - truth["yaw_rad"], math.tau))), 4
            )
            values["offset_error_m"] = round(math.hypot(x_m - truth["x_m"], y_m - truth["y_m"]), 5)
            line += (
                f", yaw by {values['yaw_error_deg']:.3f} deg, "
                f"position by {1000 * values['offset_error_m']:.1f} mm"
            )
        report.append(line)
    text = (
        "# vlp-agent calibrate mount: the camera's place on the base, for the robot config (docs/config.md)\n"
        + "".join(f"# {line}\n" for line in report)
        + "\n[vlp.mount]\n"
        + f"x_m = {x_m:.5f}\ny_m = {y_m:.5f}\nz_m = {nominal.z_m}\n"
        + f"yaw_rad = {yaw:.6f}\nroll_rad = {roll:.6f}\npitch_rad = {pitch:.6f}\n"
    )
    panels = [plot.text_panel(report + [c.describe() for c in checks], title="camera mount")]
    if poses:
        board = np.array([p.level(roll, pitch)[0][:2] for p in poses + shifts])
        panels.insert(
            0,
            plot.scatter(
                [plot.Series(board, plot.BLUE, "board centre in the level camera frame", 4, line=True)],
                title="board positions: headings 0, 180, 0, ahead, back",
                axis_labels=("x (m)", "y (m)"),
            ),
        )
    advice = [f"copy the [vlp.mount] table from {output} into the robot config"]
    if not all(c.ok for c in checks):
        advice.insert(
            0,
            "the measurements disagree: keep the robot still while it measures, hold the board level "
            "and steady, and check the camera calibration",
        )
    else:
        advice.append("next: `vlp-agent calibrate leds` (survey the ceiling LEDs)")
    outputs = [
        Output(output, text),
        Output(output.with_suffix(".png"), plot.png(plot.grid(panels)), report=True),
    ]
    return StepResult(NAME, values, checks, report, advice, outputs)
