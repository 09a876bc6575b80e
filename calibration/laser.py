"""Step ``laser``: where the laser sits on the base (yaw, x, y) from a room corner.

The robot faces a corner 1-2 m away. Each scan is cut into straight walls (split-and-merge, then a total least
squares line per wall); the corner is where two walls meeting at 60-120 degrees cross. Then:

* **Yaw.** The robot drives straight ahead a little and back. A fixed point moves in the laser frame by
  t = d (cos psi, -sin psi) for a base move of d along its own x axis, so psi = atan2(-t_y, t_x), whatever d.
  (The walls' directions also give any rotation during the drive, which is taken out first.)
* **Offset.** The robot turns in place a few times by about +-30 degrees about the middle of its axle (base
  origin). The walls' directions give each turn's angle delta_k exactly, and the corner c_k satisfies
  R(psi) c_k = R(-delta_k) p - m (p: the corner in the base frame at the start, m: the laser's position on the
  base), linear in p and m: least squares over the turns.

The laser's height cannot be seen in a planar scan; the present value is kept. With ``--sim`` the robot is
built with the laser a little turned and off its drawn place (``calibration.sim.as_built``) and put in front
of a corner of the world.
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from calibration import plot
from calibration.context import StepContext
from calibration.report import CalibrationError, Check, Output, StepResult
from calibration.rig import Rig
from calibration.wheels import drive
from drivers.errors import DeviceTimeout
from drivers.laser.base import LaserScanner
from drivers.sim.world import Mount

__all__ = [
    "Corner",
    "Line",
    "add_arguments",
    "extract_lines",
    "find_corner",
    "fit_offset",
    "interactive",
    "run",
    "yaw_from_shift",
]

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

NAME = "laser"
DEFAULT_FILE = "laser.toml"
YAW_SPREAD_DEG = 0.5
OFFSET_RMS_M = 0.01


# -- geometry (pure) ---------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Line:
    """A wall: points on it, its centre, its direction (rad, mod pi), its ends, and the fit's rms (m)."""

    centre: FloatArray
    angle_rad: float
    ends: tuple[FloatArray, FloatArray]
    points: int
    rms_m: float

    @property
    def direction(self) -> FloatArray:
        return np.array([math.cos(self.angle_rad), math.sin(self.angle_rad)])

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(self.ends[1] - self.ends[0]))


@dataclass(frozen=True, slots=True)
class Corner:
    point: FloatArray
    walls: tuple[Line, Line]


def _fit_line(pts: FloatArray) -> Line:
    """Total least squares: the line through the centroid along the principal direction."""
    centre = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centre, full_matrices=False)
    d = vt[0]
    t = (pts - centre) @ d
    normal = np.array([-d[1], d[0]])
    rms = float(np.sqrt(np.mean(((pts - centre) @ normal) ** 2)))
    return Line(centre, math.atan2(d[1], d[0]), (centre + t.min() * d, centre + t.max() * d), len(pts), rms)


def _split(pts: FloatArray, tolerance_m: float, min_points: int) -> list[FloatArray]:
    """Split-and-merge's split: cut at the point farthest from the chord until every piece is straight."""
    if len(pts) < min_points:
        return []
    a, b = pts[0], pts[-1]
    chord = b - a
    length = float(np.linalg.norm(chord))
    if length < 1e-9:
        return []
    normal = np.array([-chord[1], chord[0]]) / length
    dist = np.abs((pts - a) @ normal)
    k = int(np.argmax(dist))
    if dist[k] <= tolerance_m:
        return [pts]
    return _split(pts[: k + 1], tolerance_m, min_points) + _split(pts[k:], tolerance_m, min_points)


def extract_lines(
    points: FloatArray, *, tolerance_m: float = 0.03, min_points: int = 12, min_length_m: float = 0.3
) -> list[Line]:
    """Straight walls in an ordered scan (N, 2): break at gaps, split until straight, fit, merge neighbours
    that are one wall."""
    if len(points) < min_points:
        return []
    ranges = np.linalg.norm(points, axis=1)
    gaps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    breaks = np.flatnonzero(gaps > 0.08 + 0.05 * ranges[1:]) + 1
    pieces: list[FloatArray] = []
    for cluster in np.split(points, breaks):
        pieces += _split(cluster, tolerance_m, min_points)
    lines = [_fit_line(p) for p in pieces]
    merged: list[Line] = []
    merged_pts: list[FloatArray] = []
    for line, pts in zip(lines, pieces, strict=True):
        if merged:
            prev = merged[-1]
            turn = abs(math.remainder(line.angle_rad - prev.angle_rad, math.pi))
            offset = abs(
                (line.centre - prev.centre) @ np.array([-math.sin(prev.angle_rad), math.cos(prev.angle_rad)])
            )
            if turn < math.radians(3.0) and offset < tolerance_m:
                merged_pts[-1] = np.vstack([merged_pts[-1], pts])
                merged[-1] = _fit_line(merged_pts[-1])
                continue
        merged.append(line)
        merged_pts.append(pts)
    return [m for m in merged if m.length_m >= min_length_m and m.rms_m <= tolerance_m]


def intersect(a: Line, b: Line) -> FloatArray | None:
    da, db = a.direction, b.direction
    det = da[0] * -db[1] + db[0] * da[1]
    if abs(det) < 1e-9:
        return None
    rhs = b.centre - a.centre
    s = (rhs[0] * -db[1] + db[0] * rhs[1]) / det
    point: FloatArray = a.centre + s * da
    return point


def find_corner(lines: list[Line], near: FloatArray | None = None, reach_m: float = 0.25) -> Corner | None:
    """Two walls meeting at 60-120 degrees, each ending within ``reach_m`` of where they cross. Nearest to
    ``near`` when given (following a corner between scans), else the most straight-ahead one."""
    best: tuple[float, Corner] | None = None
    for i, a in enumerate(lines):
        for b in lines[i + 1 :]:
            angle = abs(math.degrees(math.remainder(a.angle_rad - b.angle_rad, math.pi)))
            if angle < 60.0:
                continue
            point = intersect(a, b)
            if point is None:
                continue
            if min(np.linalg.norm(e - point) for e in a.ends) > reach_m:
                continue
            if min(np.linalg.norm(e - point) for e in b.ends) > reach_m:
                continue
            score = (
                float(np.linalg.norm(point - near))
                if near is not None
                else abs(math.atan2(point[1], point[0]))
            )
            if best is None or score < best[0]:
                best = (score, Corner(point, (a, b)))
    return best[1] if best is not None else None


def wall_turn(before: Corner, after: Corner, expected_rad: float = 0.0) -> float:
    """How far the laser turned between two views of a corner, from its walls' directions: the mean over the
    two walls, each matched to the direction nearest what the ``expected`` turn predicts (walls at right
    angles look alike after a turn of more than 45 degrees)."""
    turns = []
    for wall in before.walls:
        # The walls seen turn opposite to the laser.
        candidates = [
            math.remainder(w.angle_rad - wall.angle_rad + expected_rad, math.pi) for w in after.walls
        ]
        turns.append(min(candidates, key=abs) - expected_rad)
    return -float(np.mean(turns))


def yaw_from_shift(shift: FloatArray) -> float:
    """The laser's yaw on the base from how far the laser moved (in its own frame) on a straight drive
    forward: t = d (cos psi, -sin psi)."""
    return math.atan2(-float(shift[1]), float(shift[0]))


def rot(angle: float) -> FloatArray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def laser_shift(before: Corner, after: Corner) -> FloatArray:
    """The laser's move, in the first laser frame, between two views of a fixed corner: c1 = R(-delta)(c0 - t)
    so t = c0 - R(delta) c1."""
    delta = wall_turn(before, after)
    shift: FloatArray = before.point - rot(delta) @ after.point
    return shift


def fit_offset(corners: list[Corner], turns_rad: list[float], yaw_rad: float) -> tuple[FloatArray, float]:
    """The laser's position m on the base from corners seen at turned headings:
    R(psi) c_k = R(-delta_k) p - m. Returns (m, rms of the fit in m)."""
    rows, rhs = [], []
    r_psi = rot(yaw_rad)
    for corner, delta in zip(corners, turns_rad, strict=True):
        r = rot(-delta)
        block = np.hstack([r, -np.eye(2)])
        rows.append(block)
        rhs.append(r_psi @ corner.point)
    a = np.vstack(rows)
    b = np.concatenate(rhs)
    solution, *_ = np.linalg.lstsq(a, b, rcond=None)
    residual = a @ solution - b
    m: FloatArray = solution[2:]
    return m, float(np.sqrt(np.mean(residual**2)))


# -- the step ------------------------------------------------------------------------------------------------
def _scan_points(laser: LaserScanner, scans: int) -> FloatArray:
    """The median of ``scans`` scans (the robot standing still), as points in the laser frame, in angle order.
    Scans queued before the call (taken while the robot was still moving) are skipped."""
    ranges: list[FloatArray] = []
    angles = None
    since_ns = time.monotonic_ns()
    while len(ranges) < scans:
        for attempt in range(3):
            try:
                scan = laser.read(timeout_s=2.0)
                break
            except DeviceTimeout:
                if attempt == 2:
                    raise
        if scan.host_time_ns < since_ns:
            continue
        r = scan.ranges_mm.astype(np.float64) / 1000.0
        r[~scan.valid_mask()] = np.nan
        ranges.append(r)
        angles = scan.angles_rad()
    assert angles is not None
    stack = np.vstack(ranges)
    # A beam must have returned in most scans (a median of one echo would keep its noise whole).
    ok = np.count_nonzero(np.isfinite(stack), axis=0) > scans // 2
    median = np.full(stack.shape[1], np.nan)
    median[ok] = np.nanmedian(stack[:, ok], axis=0)
    pts: FloatArray = np.column_stack([median[ok] * np.cos(angles[ok]), median[ok] * np.sin(angles[ok])])
    return pts


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--drive-m", type=float, default=0.3, help="straight drive towards the corner (default 0.3)"
    )
    p.add_argument("--turn-deg", type=float, default=30.0, help="turns each way in place (default 30)")
    p.add_argument("--scans", type=int, default=5, help="scans averaged at each stop (default 5)")


def interactive(ctx: StepContext, options: argparse.Namespace) -> argparse.Namespace:
    return options


def run(ctx: StepContext, options: argparse.Namespace) -> StepResult:
    console = ctx.console
    ctx.require_robot("the laser calibration")
    if not 0.1 <= options.drive_m <= 1.0 or not 10.0 <= options.turn_deg <= 60.0:
        raise CalibrationError("--drive-m must be 0.1-1 m and --turn-deg 10-60 degrees")
    output = ctx.output(options.output, DEFAULT_FILE)
    truth: Mount | None = None
    if ctx.sim is not None:
        from calibration.sim import as_built, corner_viewpoint, with_start

        design = ctx.sim.load()
        try:
            start = corner_viewpoint(design)
        except ValueError as exc:
            raise CalibrationError(f"world {design.name!r}: {exc}") from exc
        built, _ = as_built(with_start(design, start), ctx.sim.seed)
        truth = built.robot.laser_mount
        rig = Rig.simulated(built, ctx.sim.seed, design=design)
        console.say(
            f"laser: the simulated robot faces a corner of {design.name!r} from {start.x_m:.2f}, "
            f"{start.y_m:.2f}"
        )
    else:
        rig = Rig.for_context(ctx)
        console.say("laser: put the robot 1-2 m from a room corner, facing it, with 0.5 m free around it")
    with rig:
        laser = rig.laser()
        servos = rig.servos()
        servos.torque(True)
        laser.start()
        r0, b0 = rig.nominal.wheel_radius_m, rig.nominal.track_m
        nominal = rig.nominal.laser_mount

        def look(near: FloatArray | None, what: str) -> Corner:
            console.status(f"  scanning ({what})")
            pts = _scan_points(laser, options.scans)
            corner = find_corner(extract_lines(pts), near)
            if corner is None:
                raise CalibrationError(
                    f"no corner in the scan ({what}): two walls meeting at 60-120 degrees, 1-2 m ahead, each "
                    "at least "
                    "0.3 m long, must be in view"
                )
            return corner

        def move(distance: float = 0.0, angle: float = 0.0) -> None:
            drive(
                servos,
                radius_m=r0,
                track_m=b0,
                distance_m=distance,
                angle_rad=angle,
                speed_mps=0.1,
                turn_radps=0.6,
                tick=lambda: None,
                status=console.status,
            )

        home = look(None, "start")
        console.say(f"  corner at {home.point[0]:.3f}, {home.point[1]:.3f} m in the laser frame")
        move(distance=options.drive_m)
        ahead = look(home.point, "after driving ahead")
        move(distance=-options.drive_m)
        back = look(home.point, "after driving back")
        yaws = [yaw_from_shift(laser_shift(home, ahead)), yaw_from_shift(-laser_shift(ahead, back))]
        yaw = float(np.mean(yaws))
        turn = math.radians(options.turn_deg)
        corners, turns = [back], [wall_turn(home, back)]
        heading = 0.0
        for angle in (turn, -2.0 * turn, turn):
            move(angle=angle)
            heading += angle
            # Where the corner should be now: turned about the base origin, near the laser's own place.
            expected = rot(-angle) @ corners[-1].point
            seen = look(expected, f"turned {math.degrees(heading):+.0f} deg")
            corners.append(seen)
            turns.append(turns[-1] + wall_turn(corners[-2], seen, angle))
        offset, rms = fit_offset(corners, [t - turns[0] for t in turns], yaw)
        laser.stop()
    console.status("")
    return _result(yaw, yaws, offset, rms, nominal, truth, corners, output)


def _result(
    yaw: float,
    yaws: list[float],
    offset: FloatArray,
    rms: float,
    nominal: Mount,
    truth: Mount | None,
    corners: list[Corner],
    output: Any,
) -> StepResult:
    spread = math.degrees(max(yaws) - min(yaws))
    checks = [
        Check("yaw: agreement of the drive ahead and back", spread, YAW_SPREAD_DEG, "deg"),
        Check("offset: rms of the turn fit", rms, OFFSET_RMS_M, "m"),
    ]
    values: dict[str, Any] = {
        "yaw_deg": round(math.degrees(yaw), 4),
        "x_m": round(float(offset[0]), 5),
        "y_m": round(float(offset[1]), 5),
        "z_m": nominal.z_m,
        "yaw_runs_deg": [round(math.degrees(v), 4) for v in yaws],
        "fit_rms_m": round(rms, 5),
        "nominal": {"x_m": nominal.x_m, "y_m": nominal.y_m, "yaw_deg": math.degrees(nominal.yaw_rad)},
    }
    report = [
        f"yaw {math.degrees(yaw):+.3f} deg (drives: "
        + ", ".join(f"{math.degrees(v):+.3f}" for v in yaws)
        + ")",
        f"position on the base x {1000 * offset[0]:+.1f} mm, y {1000 * offset[1]:+.1f} mm (height kept: "
        f"{nominal.z_m} m)",
        f"was: yaw {math.degrees(nominal.yaw_rad):+.3f} deg, x {1000 * nominal.x_m:+.1f} mm, y "
        f"{1000 * nominal.y_m:+.1f} mm",
    ]
    if truth is not None:
        values["yaw_error_deg"] = round(abs(math.degrees(math.remainder(yaw - truth.yaw_rad, math.tau))), 4)
        values["offset_error_m"] = round(math.hypot(offset[0] - truth.x_m, offset[1] - truth.y_m), 5)
        values["truth"] = {"x_m": truth.x_m, "y_m": truth.y_m, "yaw_deg": math.degrees(truth.yaw_rad)}
        report.append(
            f"against the simulated robot: yaw off by {values['yaw_error_deg']:.3f} deg "
            f"(design {abs(math.degrees(truth.yaw_rad - nominal.yaw_rad)):.2f}), position off by "
            f"{1000 * values['offset_error_m']:.1f} mm (design "
            f"{1000 * math.hypot(truth.x_m - nominal.x_m, truth.y_m - nominal.y_m):.1f})"
        )
    text = (
        "# vlp-agent calibrate laser: the laser's place on the base, for the robot config (docs/config.md)\n"
        + "".join(f"# {line}\n" for line in report)
        + "\n[slam.laser_mount]\n"
        + f"x_m = {offset[0]:.5f}\ny_m = {offset[1]:.5f}\nz_m = {nominal.z_m}\nyaw_rad = {yaw:.6f}\n"
    )
    series = [
        plot.Series(np.array([c.point for c in corners]), plot.RED, "corner at each stop", 4, line=True),
    ]
    for c in corners[:1]:
        for wall in c.walls:
            label = "" if len(series) > 1 else "walls seen at the first stop"
            series.append(plot.Series(np.array(wall.ends), plot.BLUE, label, 2, line=True))
    figure = plot.grid(
        [
            plot.scatter(
                [*series, plot.Series(np.zeros((1, 2)), plot.BLACK, "laser", 4)],
                title="corner in the laser frame",
                axis_labels=("x (m)", "y (m)"),
            ),
            plot.text_panel(report + [c.describe() for c in checks], title="laser mount"),
        ]
    )
    advice = [f"copy the [slam.laser_mount] table from {output} into the robot config"]
    if not all(c.ok for c in checks):
        advice.insert(
            0,
            "the measurements disagree: check that nothing moved near the corner and the floor is level, "
            "then run again",
        )
    outputs = [Output(output, text), Output(output.with_suffix(".png"), plot.png(figure), report=True)]
    return StepResult(NAME, values, checks, report, advice, outputs)
