"""Step ``leds``: survey the ceiling LEDs into the LED map: each one's signature, measured, and its place.

For each LED in turn the robot stands under it (the user puts it there; on the simulated robot it drives
there by its odometry), the camera takes ``--frames`` frames, and the LED nearest the middle of the picture is
found and its stripes read with the VLP pipeline's own detector and decoder (``agent.vlp.detect``,
``agent.vlp.decode``): frequency f = 1 / (P t_row_eff) and duty, the median over the frames, with their
spread. Coordinates come from a CSV file (``id,x_m,y_m,z_m[,diameter_m][,survey_sigma_m]``) or are typed.
Two LEDs with different ids whose signatures are too close for the camera to tell apart are reported (closer
than three times their combined spread, or than 150 Hz and 0.08 duty); so is one id measured with two
signatures. The result is the LED map (TOML ``[[leds]]``, the format the robot config's ``[vlp] led_map``
reads).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import itertools
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agent.vlp.decode import StripeDecoder
from agent.vlp.detect import DetectorConfig, find_blobs
from agent.vlp.model import CameraIntrinsics, LedMap, MapLed
from agent.vlp.signatures import check_signatures
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
from calibration.vlp_view import view_for
from calibration.wheels import go_to
from drivers.camera.base import Camera

__all__ = [
    "LedEntry",
    "Measured",
    "add_arguments",
    "close_pairs",
    "interactive",
    "measure",
    "read_coordinates",
    "run",
]

log = logging.getLogger(__name__)

NAME = "leds"
DEFAULT_FILE = "leds.toml"
# Two signatures closer than this (and than three times their spread) cannot be told apart reliably.
MIN_SEPARATION_HZ = 150.0
MIN_SEPARATION_DUTY = 0.08
# How precisely the map's values must be known: the standard error of each median (1.2533 sigma / sqrt(n)).
MAX_FREQUENCY_ERROR = 0.01  # relative
MAX_DUTY_ERROR = 0.02


@dataclass(frozen=True, slots=True)
class LedEntry:
    """An LED as the survey gives it: where it is."""

    id: str
    x_m: float
    y_m: float
    z_m: float
    diameter_m: float = 0.086
    # The survey's standard deviation of x and y, when it states one (written to the map; docs/config.md).
    survey_sigma_m: float | None = None


@dataclass(frozen=True, slots=True)
class Measured:
    """An LED's signature as the camera saw it: medians over the frames, their spreads, frames used."""

    entry: LedEntry
    frequency_hz: float
    duty: float
    frequency_spread_hz: float
    duty_spread: float
    frames: int
    frames_tried: int

    @property
    def frequency_error_hz(self) -> float:
        """Standard error of the median frequency (1.2533 sigma / sqrt(n) for normal scatter)."""
        return 1.2533 * self.frequency_spread_hz / math.sqrt(self.frames) if self.frames > 1 else math.inf

    @property
    def duty_error(self) -> float:
        return 1.2533 * self.duty_spread / math.sqrt(self.frames) if self.frames > 1 else math.inf


def read_coordinates(path: Path) -> list[LedEntry]:
    """LED coordinates from CSV: a header with id, x_m, y_m, z_m (and optionally diameter_m and
    survey_sigma_m, the survey's standard deviation of x and y; an empty cell: none stated)."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise CalibrationError(f"cannot read {path}: {exc.strerror or exc}") from exc
    rows = list(csv.reader(text.splitlines()))
    if not rows:
        raise CalibrationError(f"{path} is empty")
    header = [h.strip() for h in rows[0]]
    missing = [k for k in ("id", "x_m", "y_m", "z_m") if k not in header]
    if missing:
        raise CalibrationError(
            f"{path} line 1: the header needs id, x_m, y_m, z_m (missing {', '.join(missing)})"
        )
    entries = []
    for line_no, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise CalibrationError(
                f"{path.name} line {line_no}: {len(row)} fields, the header has {len(header)}"
            )
        cells = dict(zip(header, (c.strip() for c in row), strict=True))
        numbers: dict[str, float] = {}
        for key in ("x_m", "y_m", "z_m", "diameter_m", "survey_sigma_m"):
            if key not in cells or (key == "survey_sigma_m" and not cells[key]):
                continue
            try:
                numbers[key] = float(cells[key])
            except ValueError:
                raise CalibrationError(
                    f"{path.name} line {line_no}: {key} {cells[key]!r} is not a number"
                ) from None
            if not math.isfinite(numbers[key]):
                raise CalibrationError(f"{path.name} line {line_no}: {key} must be finite")
        if not 0.0 <= numbers.get("survey_sigma_m", 0.0) <= 1.0:
            raise CalibrationError(f"{path.name} line {line_no}: survey_sigma_m must be in [0, 1] m")
        if not cells["id"]:
            raise CalibrationError(f"{path.name} line {line_no}: the id is empty")
        entries.append(
            LedEntry(
                cells["id"],
                numbers["x_m"],
                numbers["y_m"],
                numbers["z_m"],
                numbers.get("diameter_m", 0.086),
                numbers.get("survey_sigma_m"),
            )
        )
    if not entries:
        raise CalibrationError(f"{path} lists no LEDs")
    return entries


def type_coordinates(console: Console, count: int) -> list[LedEntry]:
    entries: list[LedEntry] = []
    z_default: float | None = None
    for k in range(1, count + 1):
        answer = ask_line(console, f"LED {k} id [L{k}]: ").strip()
        led_id = answer or f"L{k}"
        x = ask_float(console, f"  {led_id} x_m", None, minimum=-1e4, maximum=1e4)
        y = ask_float(console, f"  {led_id} y_m", None, minimum=-1e4, maximum=1e4)
        z = ask_float(
            console, f"  {led_id} z_m (height above the floor)", z_default, minimum=0.3, maximum=50.0
        )
        z_default = z
        entries.append(LedEntry(led_id, x, y, z))
    return entries


def measure(
    frames: list[Any], decoder: StripeDecoder, t_row_eff_s: float, min_diameter_px: float
) -> tuple[list[float], list[float]]:
    """Frequencies and duties read from the LED nearest the middle of each frame (not at the border)."""
    config = DetectorConfig(min_diameter_px=min_diameter_px, bridge_px=1.5 * min_diameter_px)
    freqs, duties = [], []
    for image in frames:
        h, w = image.shape[:2]
        blobs = [b for b in find_blobs(image, config) if not b.at_border]
        if not blobs:
            continue
        blob = min(blobs, key=lambda b: math.hypot(b.centre_px[0] - w / 2, b.centre_px[1] - h / 2))
        features = decoder.features(image, blob.centre_px, blob.radius_px, blob.background_dn, t_row_eff_s)
        if math.isfinite(features.frequency_hz) and math.isfinite(features.duty):
            freqs.append(features.frequency_hz)
            duties.append(features.duty)
    return freqs, duties


def _spread(values: list[float]) -> float:
    """A robust standard deviation: 1.4826 x the median absolute deviation."""
    if len(values) < 2:
        return math.nan
    a = np.asarray(values)
    return float(1.4826 * np.median(np.abs(a - np.median(a))))


def close_pairs(measured: list[Measured]) -> list[tuple[Measured, Measured, str]]:
    """Pairs the camera cannot reliably tell apart (different ids), and ids measured with two signatures."""
    out = []
    for a, b in itertools.combinations(measured, 2):
        df = abs(a.frequency_hz - b.frequency_hz)
        dd = abs(a.duty - b.duty)
        sf = 3.0 * (np.nan_to_num(a.frequency_spread_hz) + np.nan_to_num(b.frequency_spread_hz))
        sd = 3.0 * (np.nan_to_num(a.duty_spread) + np.nan_to_num(b.duty_spread))
        alike = df < max(MIN_SEPARATION_HZ, sf) and dd < max(MIN_SEPARATION_DUTY, sd)
        if a.entry.id != b.entry.id and alike:
            out.append(
                (
                    a,
                    b,
                    f"{a.entry.id} and {b.entry.id} are too close to tell apart ({df:.0f} Hz, {dd:.2f} duty "
                    "apart)",
                )
            )
        elif a.entry.id == b.entry.id and not alike:
            out.append(
                (
                    a,
                    b,
                    f"{a.entry.id} was measured with two signatures ({a.frequency_hz:.0f} Hz / {a.duty:.2f} "
                    f"and {b.frequency_hz:.0f} Hz / {b.duty:.2f}): two LEDs sharing an id must blink alike",
                )
            )
    return out


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--coordinates", metavar="CSV", help="LED coordinates: id,x_m,y_m,z_m[,diameter_m]")
    p.add_argument(
        "--count",
        type=int,
        default=None,
        help="how many LEDs to type in (without --coordinates); --sim: survey the world's first N",
    )
    p.add_argument("--frames", type=int, default=20, help="frames measured per LED (default 20)")
    p.add_argument(
        "--led-diameter-mm", type=float, default=86.0, help="LED diameter for typed LEDs (default 86)"
    )


def interactive(ctx: StepContext, options: argparse.Namespace) -> argparse.Namespace:
    if ctx.sim is not None:
        ctx.console.say("LED coordinates: from the world file (the simulated ceiling is known)")
        return options
    answer = ask_line(ctx.console, "LED coordinates from a CSV file (path), or Enter to type them: ").strip()
    options.coordinates = answer or None
    return options


def world_coordinates(ctx: StepContext, count: int | None) -> list[LedEntry]:
    """The simulated robot's LEDs where its world file puts them: what a survey with a tape measure would
    give on a real ceiling, so nothing is asked (the first ``count`` of them with --count)."""
    assert ctx.sim is not None
    leds = ctx.sim.load().leds
    if not leds:
        raise CalibrationError(f"the world {ctx.sim.world_file} has no LEDs to survey")
    chosen = leds if count is None else leds[:count]
    return [LedEntry(led.id, led.x_m, led.y_m, led.z_m, led.diameter_m, led.survey_sigma_m) for led in chosen]


def run(ctx: StepContext, options: argparse.Namespace) -> StepResult:
    console = ctx.console
    output = ctx.output(options.output, DEFAULT_FILE)
    if options.frames < 3:
        raise CalibrationError("--frames must be at least 3")
    ctx.require_robot("the LED survey")
    if options.count is not None and options.count < 1:
        raise CalibrationError("--count must be at least 1")
    if options.coordinates:
        entries = read_coordinates(Path(options.coordinates))
    elif ctx.sim is not None:
        entries = world_coordinates(ctx, options.count)
        console.say(f"  LED coordinates: {len(entries)} from the world file {ctx.sim.world_file.name}")
    else:
        count = options.count
        if count is None:
            count = ask_int(console, "how many LEDs", None, minimum=1, maximum=500)
        entries = type_coordinates(console, count)
    if options.led_diameter_mm != 86.0:
        entries = [dataclasses.replace(e, diameter_m=options.led_diameter_mm / 1000.0) for e in entries]
    view = view_for(ctx)
    intrinsics, mount = view.intrinsics, view.mount
    decoder = StripeDecoder()
    measured: list[Measured] = []
    truth: dict[str, tuple[float, float]] = {}
    if ctx.sim is not None:
        truth = {led.id: (led.frequency_hz, led.duty) for led in ctx.sim.load().leds}
    with Rig.for_context(ctx) as rig:
        camera = rig.camera()
        pose: tuple[float, float, float] | None = None
        if rig.simulation is not None:
            servos = rig.servos()
            servos.torque(True)
            start = rig.simulation.world.robot.start
            pose = (start.x_m, start.y_m, start.yaw_rad)
        for n, entry in enumerate(entries, start=1):
            if pose is not None:
                console.say(f"  LED {n}/{len(entries)} {entry.id}: driving under it")
                pose = go_to(
                    servos,
                    pose,
                    (entry.x_m - mount.x_m, entry.y_m - mount.y_m),
                    radius_m=rig.nominal.wheel_radius_m,
                    track_m=rig.nominal.track_m,
                    speed_mps=0.25,
                    turn_radps=1.5,
                    status=console.status,
                )
            else:
                ask_line(
                    console,
                    f"  LED {n}/{len(entries)} {entry.id}: put the robot under it (the LED near the middle "
                    "of "
                    "the picture), then press Enter ",
                )
            frames = _grab(camera, options.frames)
            height = max(entry.z_m - mount.z_m, 0.1)
            diameter_px = intrinsics.fx_px * entry.diameter_m / height
            freqs, duties = measure(frames, decoder, intrinsics.t_row_eff_s, max(0.5 * diameter_px, 6.0))
            console.status("")
            if len(freqs) < max(2, len(frames) // 2):
                raise CalibrationError(
                    f"LED {entry.id}: its stripes were read in only {len(freqs)} of {len(frames)} frames. Is "
                    "it on, "
                    "in view and not at the border of the picture? (The camera's exposure must be the VLP "
                    "one, "
                    "short enough for stripes.)"
                )
            m = Measured(
                entry,
                float(np.median(freqs)),
                float(np.median(duties)),
                _spread(freqs),
                _spread(duties),
                len(freqs),
                len(frames),
            )
            measured.append(m)
            console.say(
                f"  {entry.id}: {m.frequency_hz:.0f} Hz (+-{m.frequency_spread_hz:.0f}), duty {m.duty:.3f} "
                f"(+-{m.duty_spread:.3f}), {m.frames}/{m.frames_tried} frames"
            )
    return _result(measured, truth, view.source, output, _camera_warnings(measured, intrinsics, mount.z_m))


def _camera_warnings(measured: list[Measured], intrinsics: CameraIntrinsics, lens_z_m: float) -> list[str]:
    """What this camera cannot tell apart in the measured map (``agent.vlp.signatures``): pairs closer than
    the decoder's resolution, stripes shorter than a row, too few stripes across a blob."""
    if not measured:
        return []
    try:
        leds = LedMap(
            tuple(
                MapLed(
                    m.entry.id,
                    m.entry.x_m,
                    m.entry.y_m,
                    m.entry.z_m,
                    m.frequency_hz,
                    m.duty,
                    m.entry.diameter_m,
                )
                for m in measured
            )
        )
    except ValueError:
        return []  # one id measured with two signatures: close_pairs says so
    return [w.message for w in check_signatures(leds, intrinsics, lens_z_m)]


def _grab(camera: Camera, count: int) -> list[Any]:
    frames = []
    for _ in range(count):
        frames.append(camera.grab(timeout_s=2.0).image)
    return frames


def format_led_map(measured: list[Measured], comment: list[str]) -> str:
    lines = ["# vlp-agent calibrate leds: the LED map (docs/calibration.md); set [vlp] led_map to this file"]
    lines += [f"# {c}" for c in comment]
    for m in measured:
        e = m.entry
        lines += [
            "",
            "[[leds]]",
            f'id = "{e.id}"',
            f"x_m = {e.x_m!r}",
            f"y_m = {e.y_m!r}",
            f"z_m = {e.z_m!r}",
            f"frequency_hz = {round(m.frequency_hz, 1)!r}",
            f"duty = {round(m.duty, 3)!r}",
            f"diameter_m = {e.diameter_m!r}",
        ]
        if e.survey_sigma_m is not None:
            lines.append(f"survey_sigma_m = {e.survey_sigma_m!r}")
    return "\n".join(lines) + "\n"


def _result(
    measured: list[Measured],
    truth: dict[str, tuple[float, float]],
    source: str,
    output: Path,
    camera_warnings: list[str] | None = None,
) -> StepResult:
    pairs = close_pairs(measured)
    camera_warnings = camera_warnings or []
    f_error = max((m.frequency_error_hz / m.frequency_hz for m in measured), default=math.inf)
    d_error = max((m.duty_error for m in measured), default=math.inf)
    checks = [
        Check("frequency standard error (worst LED)", 100.0 * f_error, 100.0 * MAX_FREQUENCY_ERROR, "%"),
        Check("duty standard error (worst LED)", d_error, MAX_DUTY_ERROR),
        Check(
            "LED pairs too close to tell apart",
            float(sum(1 for a, b, _ in pairs if a.entry.id != b.entry.id)),
            0.0,
        ),
        Check(
            "ids measured with two signatures",
            float(sum(1 for a, b, _ in pairs if a.entry.id == b.entry.id)),
            0.0,
        ),
    ]
    report = [
        f"{m.entry.id}: ({m.entry.x_m:.3f}, {m.entry.y_m:.3f}, {m.entry.z_m:.3f}) m, {m.frequency_hz:.1f} "
        "Hz, duty "
        f"{m.duty:.3f}"
        for m in measured
    ]
    report += [f"WARNING: {text}" for _, _, text in pairs]
    report += [f"WARNING (this camera): {text}" for text in camera_warnings]
    values: dict[str, Any] = {
        "leds": [
            {
                "id": m.entry.id,
                "x_m": m.entry.x_m,
                "y_m": m.entry.y_m,
                "z_m": m.entry.z_m,
                "frequency_hz": round(m.frequency_hz, 2),
                "duty": round(m.duty, 4),
                "frequency_spread_hz": round(m.frequency_spread_hz, 2),
                "duty_spread": round(m.duty_spread, 4),
                "frames": m.frames,
            }
            for m in measured
        ],
        "warnings": [text for _, _, text in pairs] + camera_warnings,
        "camera": source,
    }
    if truth:
        errors = [
            (
                abs(m.frequency_hz - truth[m.entry.id][0]) / truth[m.entry.id][0],
                abs(m.duty - truth[m.entry.id][1]),
            )
            for m in measured
            if m.entry.id in truth
        ]
        if errors:
            values["frequency_error_pct_max"] = round(100.0 * max(e[0] for e in errors), 3)
            values["duty_error_max"] = round(max(e[1] for e in errors), 4)
            report.append(
                f"against the simulated LEDs: frequency within {values['frequency_error_pct_max']:.2f} %, "
                f"duty within {values['duty_error_max']:.3f}"
            )
    text = format_led_map(measured, [f"signatures measured with the camera ({source})"])
    sig = np.array([[m.frequency_hz, 1000.0 * m.duty] for m in measured])
    where = np.array([[m.entry.x_m, m.entry.y_m] for m in measured])
    ids = [m.entry.id for m in measured]
    figure = plot.grid(
        [
            plot.scatter(
                [plot.Series(where, plot.ORANGE, "LED (its id beside it)", 6, labels=ids)],
                title="LED map: where each LED is",
                axis_labels=("x (m)", "y (m)"),
            ),
            plot.scatter(
                [plot.Series(sig, plot.BLUE, "LED signature (its id beside it)", 5, labels=ids)],
                title="signatures; a circle: half the least separation",
                axis_labels=("frequency (Hz)", "duty (x 1000)"),
                circles=[
                    (float(m.frequency_hz), 1000.0 * m.duty, MIN_SEPARATION_HZ / 2, plot.GREY)
                    for m in measured
                ],
            ),
            plot.text_panel(report + [c.describe() for c in checks], title="LED survey"),
        ]
    )
    advice = [f'set led_map = "{output}" in the [vlp] table of the robot config']
    if pairs:
        advice.insert(
            0,
            "LEDs that cannot be told apart give wrong ids: change one of them (another frequency or duty "
            "on its driver), or give both the same id if they are far apart",
        )
    else:
        advice.append("next: `vlp-agent calibrate vlp-error` (needs this map)")
    outputs = [Output(output, text), Output(output.with_suffix(".png"), plot.png(figure), report=True)]
    return StepResult(NAME, values, checks, report, advice, outputs)
