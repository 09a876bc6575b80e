"""Step ``wheels``: wheel radius and track from measured straight runs and turns in place.

The robot drives a straight run forward and one back, each ``--distance-m`` by its present odometry, and
turns in place ``--turns`` full turns one way and then the other. After each, the user measures what really
happened (the distance between the marks on the floor; how far past the start heading it stopped) and the
encoders say how far each wheel turned:

    straight:  r = D / ((dphi_l + dphi_r) / 2)            (D measured, dphi wheel angles in rad)
    turn:      b = r (dphi_r - dphi_l) / Theta            (Theta measured, b the track)

Two runs of each kind give two estimates; how well they agree is the verdict. With ``--sim`` the robot is
built with a worn tyre and a track off the drawing (``calibration.sim.as_built``), and the "tape measure" is
the simulation's truth read to the millimetre and the tenth of a degree.
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from calibration import plot
from calibration.context import StepContext
from calibration.report import CalibrationError, Check, Console, Output, StepResult, ask_float
from calibration.rig import Rig
from drivers.errors import DeviceTimeout
from drivers.samples import WheelState
from drivers.servos.base import WheelServos
from drivers.sim.simulation import Simulation

__all__ = ["Run", "WheelFit", "add_arguments", "fit_wheels", "interactive", "run"]

log = logging.getLogger(__name__)

NAME = "wheels"
DEFAULT_FILE = "wheels.toml"
_TICK_S = 0.02
# Thresholds: two runs must agree this well, and the result must be this close to the design.
RADIUS_SPREAD_PCT = 0.5
TRACK_SPREAD_PCT = 1.0
PLAUSIBLE_PCT = 10.0


@dataclass(frozen=True, slots=True)
class Run:
    """One manoeuvre: wheel angle changes (rad, forward positive) and what was measured (m or rad)."""

    kind: str  # "straight" or "turn"
    dphi_left_rad: float
    dphi_right_rad: float
    measured: float


@dataclass(frozen=True, slots=True)
class WheelFit:
    wheel_radius_m: float
    track_m: float
    radius_runs_m: tuple[float, ...]
    track_runs_m: tuple[float, ...]

    @property
    def radius_spread_pct(self) -> float:
        return 100.0 * (max(self.radius_runs_m) - min(self.radius_runs_m)) / self.wheel_radius_m

    @property
    def track_spread_pct(self) -> float:
        return 100.0 * (max(self.track_runs_m) - min(self.track_runs_m)) / self.track_m


def fit_wheels(runs: list[Run]) -> WheelFit:
    """Radius from the straight runs, then track from the turns with that radius."""
    straight = [r for r in runs if r.kind == "straight"]
    turns = [r for r in runs if r.kind == "turn"]
    if not straight or not turns:
        raise CalibrationError("need at least one straight run and one turn")
    radii = []
    for r in straight:
        # r = D / mean wheel angle; a run backwards has negative angles and a positive measured distance.
        mean_angle = abs(r.dphi_left_rad + r.dphi_right_rad) / 2.0
        if mean_angle < 1.0:
            raise CalibrationError("a straight run turned the wheels less than a radian: drive further")
        radii.append(r.measured / mean_angle)
    radius = float(np.mean(radii))
    tracks = []
    for r in turns:
        if abs(r.measured) < math.pi:
            raise CalibrationError("a turn must be at least half a turn")
        tracks.append(radius * abs(r.dphi_right_rad - r.dphi_left_rad) / abs(r.measured))
    return WheelFit(radius, float(np.mean(tracks)), tuple(radii), tuple(tracks))


# -- measuring ------------------------------------------------------------------------------------------
class Measurer(Protocol):
    def start(self) -> None: ...

    def distance_m(self, question: str, nominal: float) -> float: ...

    def turn_rad(self, question: str, turns: float) -> float: ...


class TapeMeasure:
    """The user measures: a distance on the floor, and how far past (or short of) the start heading the robot
    stopped after its turns."""

    def __init__(self, console: Console) -> None:
        self.console = console

    def start(self) -> None:
        pass

    def distance_m(self, question: str, nominal: float) -> float:
        return ask_float(self.console, question, None, minimum=0.05 * nominal, maximum=10.0 * nominal)

    def turn_rad(self, question: str, turns: float) -> float:
        extra = ask_float(self.console, question, None, minimum=-90.0, maximum=90.0)
        return math.radians(360.0 * turns + extra) * math.copysign(1.0, turns)


class SimMeasurer:
    """The simulation's truth, read as a careful person would: to the millimetre, to the tenth of a degree.
    Turns are followed while they happen (:meth:`follow`), so whole turns are counted."""

    def __init__(self, simulation: Simulation) -> None:
        self.sim = simulation
        self._start = simulation.pose()
        self._turned = 0.0
        self._yaw = self._start.yaw_rad

    def start(self) -> None:
        self._start = self.sim.pose()
        self._turned = 0.0
        self._yaw = self._start.yaw_rad

    def follow(self) -> None:
        yaw = self.sim.pose().yaw_rad
        self._turned += math.remainder(yaw - self._yaw, math.tau)
        self._yaw = yaw

    def distance_m(self, question: str, nominal: float) -> float:
        end = self.sim.pose()
        return round(math.hypot(end.x_m - self._start.x_m, end.y_m - self._start.y_m), 3)

    def turn_rad(self, question: str, turns: float) -> float:
        self.follow()
        return math.radians(round(math.degrees(self._turned), 1))


# -- driving --------------------------------------------------------------------------------------------
def read_wheels(servos: WheelServos, attempts: int = 5) -> WheelState:
    """The wheels' state, riding out a few missed replies (a busy bus, a loaded computer): the angles are
    absolute, so a late reading loses nothing."""
    for attempt in range(attempts):
        try:
            return servos.read()
        except DeviceTimeout as exc:
            log.warning("wheel read %d of %d timed out: %s", attempt + 1, attempts, exc)
            time.sleep(0.02)
    raise CalibrationError(f"the wheel servos stopped answering ({attempts} reads in a row timed out)")


def _command(servos: WheelServos, left: float, right: float) -> None:
    try:
        servos.set_velocity(left, right)
    except DeviceTimeout as exc:
        log.warning("wheel command lost: %s", exc)


def _settle(servos: WheelServos, timeout_s: float = 3.0) -> WheelState:
    """Stop and wait until both wheels stand still; the wheel angles then."""
    servos.stop()
    deadline = time.monotonic() + timeout_s
    state = read_wheels(servos)
    while time.monotonic() < deadline:
        time.sleep(0.05)
        state = read_wheels(servos)
        if max(abs(v) for v in state.velocity_radps) < 0.02:
            break
    return state


def drive(
    servos: WheelServos,
    *,
    radius_m: float,
    track_m: float,
    distance_m: float = 0.0,
    angle_rad: float = 0.0,
    speed_mps: float,
    turn_radps: float,
    tick: Callable[[], None],
    status: Callable[[str], None],
) -> tuple[float, float]:
    """Drive ``distance_m`` straight (signed) or turn ``angle_rad`` in place (signed), measured by the
    present odometry (``radius_m``, ``track_m``), slowing down for the last part. Returns the wheel angles'
    (left, right) once the robot has stopped."""
    start = _settle(servos)
    goal = abs(distance_m) if distance_m else abs(angle_rad)
    sign = math.copysign(1.0, distance_m if distance_m else angle_rad)
    top = speed_mps if distance_m else turn_radps
    done = 0.0
    deadline = time.monotonic() + 4.0 * goal / (0.25 * top) + 5.0
    while done < goal:
        if time.monotonic() > deadline:
            servos.stop()
            raise CalibrationError(
                "the robot did not get there in time: is it blocked, or are the wheels off?"
            )
        state = read_wheels(servos)
        dl = state.position_rad[0] - start.position_rad[0]
        dr = state.position_rad[1] - start.position_rad[1]
        # Progress by odometry: the distance r (dl + dr) / 2, or the turn r (dr - dl) / track.
        done = sign * radius_m * ((dl + dr) / 2.0 if distance_m else (dr - dl) / track_m)
        left = goal - done
        # Trapezoid: full speed, then down to a fifth over the last stretch so the stop lands on the mark.
        slow = 0.15 if distance_m else 0.6
        speed = top * max(0.2, min(1.0, left / slow))
        if distance_m:
            wheel = sign * speed / radius_m
            _command(servos, wheel, wheel)
        else:
            wheel = sign * speed * track_m / 2.0 / radius_m
            _command(servos, -wheel, wheel)
        tick()
        unit = "m" if distance_m else "deg"
        shown = done if distance_m else math.degrees(done)
        target = goal if distance_m else math.degrees(goal)
        status(f"  {shown:7.3f} / {target:.3f} {unit}")
        time.sleep(_TICK_S)
    end = _settle(servos)
    status("")
    return end.position_rad[0] - start.position_rad[0], end.position_rad[1] - start.position_rad[1]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--distance-m", type=float, default=1.0, help="length of each straight run (default 1.0)")
    p.add_argument("--turns", type=float, default=2.0, help="full turns in place each way (default 2)")
    p.add_argument("--speed-mps", type=float, default=0.15, help="straight-run speed (default 0.15)")
    p.add_argument("--turn-radps", type=float, default=1.2, help="turning rate (default 1.2 rad/s)")


def interactive(ctx: StepContext, options: argparse.Namespace) -> argparse.Namespace:
    options.distance_m = ask_float(
        ctx.console, "length of the straight runs, m", options.distance_m, minimum=0.2, maximum=5.0
    )
    return options


def run(ctx: StepContext, options: argparse.Namespace) -> StepResult:
    console = ctx.console
    if not 0.2 <= options.distance_m <= 5.0:
        raise CalibrationError("--distance-m must be between 0.2 and 5 m")
    if not 0.5 <= options.turns <= 5.0:
        raise CalibrationError("--turns must be between 0.5 and 5")
    output = ctx.output(options.output, DEFAULT_FILE)
    ctx.require_robot("the wheel calibration")
    truth: dict[str, float] | None = None
    if ctx.sim is not None:
        from calibration.sim import as_built

        design = ctx.sim.load()
        built, _ = as_built(design, ctx.sim.seed)
        rig = Rig.simulated(built, ctx.sim.seed, design=design)
        truth = {"wheel_radius_m": built.robot.wheel_radius_m, "track_m": built.robot.track_m}
    else:
        rig = Rig.for_context(ctx)
    with rig:
        servos = rig.servos()
        servos.torque(True)
        r0, b0 = rig.nominal.wheel_radius_m, rig.nominal.track_m
        measurer: Any = SimMeasurer(rig.simulation) if rig.simulation is not None else TapeMeasure(console)
        tick: Callable[[], None] = measurer.follow if isinstance(measurer, SimMeasurer) else (lambda: None)
        console.say(
            f"wheels: present values radius {1000 * r0:.2f} mm, track {1000 * b0:.1f} mm. Mark the floor at "
            "the "
            "robot's centre and heading; the robot will drive, then ask what you measured."
        )
        runs: list[Run] = []
        d = options.distance_m
        for n, sign in enumerate((1.0, -1.0)):
            console.say(f"  straight run {n + 1}: {'forward' if sign > 0 else 'back'} {d:.2f} m")
            measurer.start()
            dl, dr = drive(
                servos,
                radius_m=r0,
                track_m=b0,
                distance_m=sign * d,
                speed_mps=options.speed_mps,
                turn_radps=options.turn_radps,
                tick=tick,
                status=console.status,
            )
            measured = measurer.distance_m("  how far did it go (m, between the marks)", d)
            runs.append(Run("straight", sign * dl, sign * dr, measured))
        for n, sign in enumerate((1.0, -1.0)):
            direction = "left (counter-clockwise)" if sign > 0 else "right (clockwise)"
            console.say(f"  turn {n + 1}: {options.turns:g} turns in place to the {direction}")
            measurer.start()
            dl, dr = drive(
                servos,
                radius_m=r0,
                track_m=b0,
                angle_rad=sign * options.turns * math.tau,
                speed_mps=options.speed_mps,
                turn_radps=options.turn_radps,
                tick=tick,
                status=console.status,
            )
            measured = measurer.turn_rad(
                "  degrees past the start heading in the turn's direction (negative if short of it)",
                sign * options.turns,
            )
            runs.append(Run("turn", sign * dl, sign * dr, abs(measured)))
    fit = fit_wheels(runs)
    return _result(fit, runs, r0, b0, truth, output)


def _result(
    fit: WheelFit, runs: list[Run], r0: float, b0: float, truth: dict[str, float] | None, output: Any
) -> StepResult:
    checks = [
        Check("radius: agreement of the two runs", fit.radius_spread_pct, RADIUS_SPREAD_PCT, "%"),
        Check("track: agreement of the two turns", fit.track_spread_pct, TRACK_SPREAD_PCT, "%"),
        Check(
            "radius: change from the present value",
            100.0 * abs(fit.wheel_radius_m / r0 - 1.0),
            PLAUSIBLE_PCT,
            "%",
        ),
        Check(
            "track: change from the present value", 100.0 * abs(fit.track_m / b0 - 1.0), PLAUSIBLE_PCT, "%"
        ),
    ]
    values: dict[str, Any] = {
        "wheel_radius_m": round(fit.wheel_radius_m, 6),
        "track_m": round(fit.track_m, 6),
        "nominal_wheel_radius_m": r0,
        "nominal_track_m": b0,
        "radius_runs_m": [round(v, 6) for v in fit.radius_runs_m],
        "track_runs_m": [round(v, 6) for v in fit.track_runs_m],
        "runs": [
            {
                "kind": r.kind,
                "dphi_left_rad": round(r.dphi_left_rad, 5),
                "dphi_right_rad": round(r.dphi_right_rad, 5),
                "measured": round(r.measured, 5),
            }
            for r in runs
        ],
    }
    report = [
        f"wheel radius {1000 * fit.wheel_radius_m:.3f} mm (was {1000 * r0:.3f}); runs "
        + ", ".join(f"{1000 * v:.3f}" for v in fit.radius_runs_m),
        f"track {1000 * fit.track_m:.2f} mm (was {1000 * b0:.2f}); turns "
        + ", ".join(f"{1000 * v:.2f}" for v in fit.track_runs_m),
    ]
    for r in runs:
        if r.kind == "straight":
            before = r0 * (r.dphi_left_rad + r.dphi_right_rad) / 2
            after = fit.wheel_radius_m * (r.dphi_left_rad + r.dphi_right_rad) / 2
            report.append(
                f"straight run: measured {r.measured:.3f} m, odometry before {before:.3f} m, after "
                f"{after:.3f} m"
            )
        else:
            before = math.degrees(r0 * (r.dphi_right_rad - r.dphi_left_rad) / b0)
            after = math.degrees(fit.wheel_radius_m * (r.dphi_right_rad - r.dphi_left_rad) / fit.track_m)
            report.append(
                f"turn: measured {math.degrees(r.measured):.1f} deg, odometry before {before:.1f}, after "
                f"{after:.1f}"
            )
    if truth is not None:
        values["wheel_radius_error_pct"] = round(
            100 * abs(fit.wheel_radius_m / truth["wheel_radius_m"] - 1), 4
        )
        values["track_error_pct"] = round(100 * abs(fit.track_m / truth["track_m"] - 1), 4)
        values["truth"] = truth
        report.append(
            f"against the simulated robot: radius off by {values['wheel_radius_error_pct']:.3f} % "
            f"(design was {100 * abs(r0 / truth['wheel_radius_m'] - 1):.2f} % off), track off by "
            f"{values['track_error_pct']:.3f} % (design {100 * abs(b0 / truth['track_m'] - 1):.2f} %)"
        )
    text = (
        "# vlp-agent calibrate wheels: the [servos] keys for the robot config (docs/config.md)\n"
        + "".join(f"# {line}\n" for line in report)
        + f"\n[servos]\nwheel_radius_m = {fit.wheel_radius_m:.6f}\ntrack_m = {fit.track_m:.6f}\n"
    )
    deviations = [100 * (v / fit.wheel_radius_m - 1) for v in fit.radius_runs_m] + [
        100 * (v / fit.track_m - 1) for v in fit.track_runs_m
    ]
    figure = plot.grid(
        [
            plot.bar_chart(
                [abs(v) for v in deviations],
                title="runs 1-2: radius, 3-4: track; |deviation from the mean|",
                ylabel="deviation (%)",
                xlabel="run",
                threshold=RADIUS_SPREAD_PCT / 2,
            ),
            plot.text_panel(report + [c.describe() for c in checks], title="wheels"),
        ]
    )
    advice = [f"copy wheel_radius_m and track_m from {output} into the [servos] table of the robot config"]
    if not checks[0].ok or not checks[1].ok:
        advice.insert(
            0,
            "the runs disagree: measure more carefully (mark the centre of the axle), check tyre "
            "pressure and that the floor is flat, and run the step again",
        )
    else:
        advice.append("next: `vlp-agent calibrate laser` (uses the wheels to drive)")
    outputs = [Output(output, text), Output(output.with_suffix(".png"), plot.png(figure), report=True)]
    return StepResult(NAME, values, checks, report, advice, outputs)


def go_to(
    servos: WheelServos,
    pose: tuple[float, float, float],
    target: tuple[float, float],
    *,
    radius_m: float,
    track_m: float,
    heading_rad: float | None = None,
    speed_mps: float = 0.2,
    turn_radps: float = 1.0,
    status: Callable[[str], None] = lambda text: None,
) -> tuple[float, float, float]:
    """Drive from ``pose`` (x, y, yaw, as the robot believes it) to ``target``: turn to face it, drive
    straight, then turn to ``heading_rad`` if given. Returns the pose after, by odometry (the wheel angles
    each move really turned, not the commands)."""
    x, y, yaw = pose

    def turn_to(angle: float) -> None:
        nonlocal yaw
        delta = math.remainder(angle - yaw, math.tau)
        if abs(delta) < math.radians(1.0):
            return
        dl, dr = drive(
            servos,
            radius_m=radius_m,
            track_m=track_m,
            angle_rad=delta,
            speed_mps=speed_mps,
            turn_radps=turn_radps,
            tick=lambda: None,
            status=status,
        )
        yaw += radius_m * (dr - dl) / track_m

    dx, dy = target[0] - x, target[1] - y
    distance = math.hypot(dx, dy)
    if distance > 0.01:
        turn_to(math.atan2(dy, dx))
        dl, dr = drive(
            servos,
            radius_m=radius_m,
            track_m=track_m,
            distance_m=distance,
            speed_mps=speed_mps,
            turn_radps=turn_radps,
            tick=lambda: None,
            status=status,
        )
        travelled = radius_m * (dl + dr) / 2.0
        x += travelled * math.cos(yaw)
        y += travelled * math.sin(yaw)
    if heading_rad is not None:
        turn_to(heading_rad)
    return x, y, yaw
