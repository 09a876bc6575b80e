"""Step ``row-time``: the camera's row time from the ceiling LEDs' known frequencies.

The stripes' clock is the sensor's row time: an LED blinking at f draws stripes P = 1 / (f t_row_eff) output
rows apart. Every frequency the decoder reads, and so every id, scales with the row time the config states;
a 2-3 % error (a sensor's line length or pixel clock not as the data sheet says) shifts every frequency by
as much. The LEDs' drivers blink at known frequencies (the LED map's), so the row time follows from the
periods measured: with the robot where several LEDs are in view (on the simulated robot it drives under
the middle of the three LEDs nearest its start and turns between batches of frames), ``--frames`` frames
are taken, each LED's stripe period fitted below the output row (``agent.vlp.decode.fit_period``), the LEDs
recognised together (``agent.vlp.row_time.recognise_signatures``: the one factor within ``--max-error`` that
puts the frequencies read on the map's signatures; signatures closer than the error, 100 Hz apart, are told
apart by the LEDs at the ends of their range; refused, with the reason, when the set cannot tell), and
t_row = 1 / (f P a) combined robustly over all sightings (``agent.vlp.row_time``: median, outliers
rejected, mean, with its uncertainty).

Run it before ``leds`` (the survey measures frequencies with the row time) with the LED map of the drivers'
frequencies (``--led-map``, or the config's). It writes ``row_time.toml``: the ``[vlp.rolling_shutter]``
``t_row_s`` to put in the robot config.
"""

from __future__ import annotations

import argparse
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agent.vlp.decode import DecoderConfig, RowTiming, StripeDecoder
from agent.vlp.detect import find_blobs
from agent.vlp.model import CameraIntrinsics, CameraMount, LedMap
from agent.vlp.pipeline import VlpPipeline
from agent.vlp.row_time import RowTimeEstimate, estimate_row_time, recognise_signatures
from calibration import plot
from calibration.context import StepContext
from calibration.report import CalibrationError, Check, Output, StepResult, ask_line
from calibration.rig import Rig
from calibration.vlp_view import view_for
from calibration.wheels import go_to

__all__ = [
    "Sightings",
    "add_arguments",
    "capture_poses",
    "estimate_from_frames",
    "interactive",
    "measure_periods",
    "run",
]

log = logging.getLogger(__name__)

NAME = "row-time"
DEFAULT_FILE = "row_time.toml"
# The estimate must be known to 0.2 % (a tenth of the row-time errors it is there to find).
MAX_RELATIVE_SIGMA = 0.002
# Every LED's own row time within 1 % of the estimate (else its frequency in the map is wrong).
MAX_LED_DEVIATION = 0.01
MIN_LEDS = 2
# Headings the simulated robot turns to between batches of frames.
_TURNS_RAD = (0.0, 0.7, -0.7)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--frames", type=int, default=30, help="frames measured (default 30)")
    p.add_argument(
        "--led-map", metavar="TOML", help="the LEDs with their drivers' frequencies (default: the config's)"
    )
    p.add_argument(
        "--max-error",
        type=float,
        default=0.05,
        help="the largest row-time error to allow for when recognising LEDs, a fraction (default 0.05): the "
        "one factor within it that puts the frequencies read on the map's signatures recognises the LEDs",
    )


def interactive(ctx: StepContext, options: argparse.Namespace) -> argparse.Namespace:
    if ctx.sim is None:
        ctx.console.say("put the robot where two or more LEDs are in view, away from the picture's border")
    return options


@dataclass(frozen=True)
class Sightings:
    """The LEDs measured for the row time: periods (output rows, below the row), the drivers' frequencies
    and ids of those recognised, how many blobs were not, and why none was when the set was ambiguous."""

    periods: list[float]
    frequencies: list[float]
    ids: list[str]
    unknown: int
    factor: float = math.nan
    refused: str | None = None


def measure_periods(frames: list[Any], pipeline: VlpPipeline, max_error: float) -> Sightings:
    """Every blob not at the border in the frames, its period fitted below the row and its duty, recognised
    all together (``agent.vlp.row_time.recognise_signatures``: the one factor within ``max_error`` that
    puts the frequencies read on the map's signatures, then each sighting the signature nearest its
    corrected frequency)."""
    intrinsics = pipeline.intrinsics
    decoder = StripeDecoder(DecoderConfig(period_fit="always"), RowTiming.of(intrinsics))
    t_eff = intrinsics.t_row_eff_s
    measured: list[tuple[float, float]] = []
    for image in frames:
        blobs = [b for b in find_blobs(image, pipeline.detector) if not b.at_border]
        if not blobs:
            continue
        requests = [(b.centre_px, b.radius_px, b.background_dn, False) for b in blobs]
        measured += [(f.period_px, f.duty) for f in decoder.features_many(image, requests, t_eff)]
    if not measured:
        return Sightings([], [], [], 0)
    match = recognise_signatures(
        [m[0] for m in measured], [m[1] for m in measured], pipeline.signatures, t_eff, max_error
    )
    if isinstance(match, str):
        return Sightings([], [], [], len(measured), refused=match)
    periods: list[float] = []
    frequencies: list[float] = []
    ids: list[str] = []
    for (period, _), sig in zip(measured, match.signatures, strict=True):
        if sig is None:
            continue
        periods.append(period)
        frequencies.append(sig.frequency_hz)
        ids.append(sig.id)
    return Sightings(periods, frequencies, ids, len(measured) - len(periods), match.factor)


def estimate_from_frames(
    frames: list[Any], intrinsics: CameraIntrinsics, leds: LedMap, mount: CameraMount, max_error: float = 0.05
) -> tuple[RowTimeEstimate | None, Sightings]:
    """The row-time step's measurement on frames already taken (what ``run`` does after the capture; the
    benchmarks call it on rendered frames): the estimate, or None when no LED was recognised."""
    sightings = measure_periods(frames, VlpPipeline(intrinsics, leds, mount), max_error)
    if not sightings.periods:
        return None, sightings
    return (
        estimate_row_time(
            sightings.periods, sightings.frequencies, sightings.ids, intrinsics.sensor_rows_per_row
        ),
        sightings,
    )


def capture_poses(
    leds: LedMap, start: tuple[float, float, float], mount: CameraMount
) -> list[tuple[float, float, float]]:
    """Where the simulated robot takes the frames (base x, y, yaw): under the middle of the three LEDs
    nearest its start, at its start heading and turned either way (``_TURNS_RAD``)."""
    x, y = _middle_of_nearest(leds, (start[0], start[1]), mount)
    return [(x, y, start[2] + turn) for turn in _TURNS_RAD]


def run(ctx: StepContext, options: argparse.Namespace) -> StepResult:
    console = ctx.console
    output = ctx.output(options.output, DEFAULT_FILE)
    if options.frames < 3:
        raise CalibrationError("--frames must be at least 3")
    if not 0.0 < options.max_error < 0.5:
        raise CalibrationError("--max-error must be between 0 and 0.5")
    ctx.require_robot("the row-time calibration")
    view = view_for(ctx, led_map=options.led_map)
    if view.led_map is None or not len(view.led_map):
        raise CalibrationError(
            "the row-time calibration needs the LEDs' frequencies: an LED map in the config, or "
            "--led-map FILE"
        )
    intrinsics, mount = view.intrinsics, view.mount
    pipeline = VlpPipeline(intrinsics, view.led_map, mount)
    truth: float | None = None
    if ctx.sim is not None:
        truth = ctx.sim.load().camera.t_row_s
    frames: list[Any] = []
    with Rig.for_context(ctx) as rig:
        camera = rig.camera()
        if rig.simulation is not None:
            servos = rig.servos()
            servos.torque(True)
            start = rig.simulation.world.robot.start
            pose = (start.x_m, start.y_m, start.yaw_rad)
            target = _middle_of_nearest(view.led_map, (start.x_m, start.y_m), mount)
            console.say(f"  driving under the LEDs near ({target[0]:.2f}, {target[1]:.2f}) m")
            batch = max(options.frames // len(_TURNS_RAD), 1)
            for k, turn in enumerate(_TURNS_RAD):
                pose = go_to(
                    servos,
                    pose,
                    target,
                    radius_m=rig.nominal.wheel_radius_m,
                    track_m=rig.nominal.track_m,
                    heading_rad=start.yaw_rad + turn,
                    speed_mps=0.25,
                    turn_radps=1.5,
                    status=console.status,
                )
                count = batch if k < len(_TURNS_RAD) - 1 else options.frames - batch * k
                frames += [camera.grab(timeout_s=2.0).image for _ in range(max(count, 0))]
        else:
            ask_line(console, "  two or more LEDs in view? press Enter to take the frames ")
            frames = [camera.grab(timeout_s=2.0).image for _ in range(options.frames)]
    console.status("")
    sightings = measure_periods(frames, pipeline, options.max_error)
    if sightings.refused is not None:
        raise CalibrationError(f"the LEDs in {len(frames)} frames cannot be recognised: {sightings.refused}")
    if not sightings.periods:
        raise CalibrationError(
            f"no LED of the map was recognised in {len(frames)} frames ({sightings.unknown} blobs not "
            "recognised): are LEDs in view, with the VLP exposure, and is --led-map the map of these LEDs? "
            f"A row time within --max-error ({options.max_error:g}) of the config's must put the frequencies "
            "read on the map's signatures"
        )
    estimate = estimate_row_time(
        sightings.periods, sightings.frequencies, sightings.ids, intrinsics.sensor_rows_per_row
    )
    result = _result(estimate, intrinsics, len(frames), sightings.unknown, truth, view.source, output)
    # What this camera cannot tell apart in the map (agent.vlp.signatures), as the pipeline says at load.
    warnings = [w.message for w in pipeline.signature_warnings]
    result.report += [f"WARNING (this camera): {text}" for text in warnings]
    result.values["warnings"] = warnings
    return result


def _middle_of_nearest(leds: LedMap, start: tuple[float, float], mount: CameraMount) -> tuple[float, float]:
    """Where the lens is under the middle of the three LEDs nearest ``start`` (the base's place for it)."""
    near = sorted(leds.leds, key=lambda led: math.hypot(led.x_m - start[0], led.y_m - start[1]))[:3]
    x = sum(led.x_m for led in near) / len(near)
    y = sum(led.y_m for led in near) / len(near)
    return x - mount.x_m, y - mount.y_m


def _result(
    estimate: RowTimeEstimate,
    intrinsics: CameraIntrinsics,
    frames: int,
    unknown: int,
    truth: float | None,
    source: str,
    output: Path,
) -> StepResult:
    t, sigma = estimate.t_row_s, estimate.sigma_s
    stated = intrinsics.t_row_s
    change = t / stated - 1.0
    deviation = estimate.led_deviation()
    worst = max((abs(v) for v in deviation.values()), default=math.nan)
    checks = [
        Check("row time uncertainty", 100.0 * estimate.relative_sigma, 100.0 * MAX_RELATIVE_SIGMA, "%"),
        Check("LEDs recognised", float(len(estimate.per_led)), float(MIN_LEDS), at_least=True),
        Check("worst LED's own row time off the estimate", 100.0 * worst, 100.0 * MAX_LED_DEVIATION, "%"),
    ]
    report = [
        f"row time {t * 1e6:.4f} us +- {sigma * 1e6:.4f} us ({100.0 * estimate.relative_sigma:.3f} %), from "
        f"{estimate.used} LED sightings in {frames} frames ({estimate.rejected} rejected as outliers, "
        f"{unknown} blobs not recognised)",
        f"the config says {stated * 1e6:.4f} us: the measured one is {100.0 * change:+.2f} % off it",
    ]
    report += [
        f"  {led}: {v * 1e6:.4f} us over {n} sightings ({100.0 * deviation[led]:+.2f} %)"
        for led, (v, n) in estimate.per_led.items()
    ]
    values: dict[str, Any] = {
        "t_row_s": t,
        "t_row_sigma_s": sigma,
        "relative_sigma": estimate.relative_sigma,
        "config_t_row_s": stated,
        "change_pct": 100.0 * change,
        "sightings": estimate.used,
        "rejected": estimate.rejected,
        "unrecognised": unknown,
        "frames": frames,
        "leds": [
            {"id": led, "t_row_s": v, "sightings": n, "deviation_pct": 100.0 * deviation[led]}
            for led, (v, n) in estimate.per_led.items()
        ],
        "camera": source,
    }
    if truth is not None:
        values["true_t_row_s"] = truth
        values["error_pct"] = 100.0 * (t / truth - 1.0)
        report.append(f"against the simulated camera ({truth * 1e6:.4f} us): {values['error_pct']:+.3f} %")
    text = "\n".join(
        [
            "# vlp-agent calibrate row-time: the camera's row time from the LEDs' known frequencies "
            "(docs/calibration.md)",
            f"# {t * 1e6:.4f} us +- {sigma * 1e6:.4f} us from {estimate.used} sightings of "
            f"{len(estimate.per_led)} LEDs; the config said {stated * 1e6:.4f} us ({100.0 * change:+.2f} %)",
            f"# camera: {source}",
            "# put t_row_s into the [vlp.rolling_shutter] table of the robot config",
            "[vlp.rolling_shutter]",
            f"t_row_s = {t:.6e}",
        ]
    )
    figure = plot.grid(
        [
            plot.bar_chart(
                [1000.0 * abs(deviation[k]) for k in estimate.per_led],
                title="each LED's own row time off the estimate",
                ylabel="|deviation| (per mille)",
                xlabel="LED (" + ", ".join(estimate.per_led) + ")",
                threshold=1000.0 * MAX_LED_DEVIATION,
            ),
            plot.text_panel(report + [c.describe() for c in checks], title="row time"),
        ]
    )
    advice = [f"set t_row_s = {t:.6e} in the [vlp.rolling_shutter] table of the robot config (from {output})"]
    if worst > MAX_LED_DEVIATION:
        advice.insert(
            0, "an LED's own row time stands apart: check its frequency in the LED map (its driver)"
        )
    else:
        advice.append("next: `vlp-agent calibrate leds` (survey the LEDs with this row time)")
    outputs = [Output(output, text + "\n"), Output(output.with_suffix(".png"), plot.png(figure), report=True)]
    return StepResult(NAME, values, checks, report, advice, outputs)
