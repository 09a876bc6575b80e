"""Step ``rfid``: the likelihood table of person following's RFID layer, from reads of a tag walked round
the robot (``docs/following.md``, ``agent/following/coarse.py``).

The coarse filter needs, per antenna port, sector and range bin, how often the tag is read in a cycle
and its RSSI's mean and spread there. The physical model gives a first guess; this step measures them:

* **On the robot** the person wearing the tag stands at marked stations round the robot (every 45 degrees
  at 1, 2 and 3 m by default, facing the robot and then turned away, as a follower sees them) and the
  reads of ``--seconds`` at each are kept, cycle by cycle, with the station's bearing and range.
* **With --sim** a scripted walk: the world's reader (``[rfid] antenna_yaws_deg``) and one person walking
  circles round the robot at several radii (those that stay clear of the walls), on a stepped clock
  through the fake reader's bytes (``drivers.sim.rfid_cycles``): minutes of walking in seconds.

The fit (:func:`agent.following.coarse.fit_table`) shrinks each cell towards the model by a few pseudo
cycles, so cells the walk missed keep the model's values. Checks: enough cells measured, and the
left/right cue reported as ``reference/eco.md`` §3 measured it (the correlation of the RSSI difference
of two ports with sin(bearing)). Writes the table (``rfid_table.toml``, for ``[following] rfid_table``).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from agent.following.coarse import (
    Antenna,
    LikelihoodTable,
    RadioModel,
    SectorGrid,
    default_table,
    fit_table,
    observation_from_reads,
)
from calibration import plot
from calibration.context import StepContext
from calibration.report import CalibrationError, Check, Output, StepResult, ask_line
from calibration.rig import Rig
from drivers.sim.world import Person, World

__all__ = ["Recording", "add_arguments", "interactive", "record_sim_walk", "run", "table_toml", "walk_path"]

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

NAME = "rfid"
DEFAULT_FILE = "rfid_table.toml"
MIN_COVERAGE = 0.5  # share of the grid's cells with at least MIN_CYCLES cycles
MIN_CYCLES = 3


@dataclass
class Recording:
    """Cycles with known truth: bearing and range (N,), per port read or not and mean RSSI (N, A), and
    whether the person had their back to the robot (N,)."""

    bearing_rad: FloatArray
    range_m: FloatArray
    detected: npt.NDArray[np.bool_]
    rssi_dbm: FloatArray
    away: npt.NDArray[np.bool_]

    def subset(self, keep: npt.NDArray[np.bool_]) -> Recording:
        return Recording(
            self.bearing_rad[keep],
            self.range_m[keep],
            self.detected[keep],
            self.rssi_dbm[keep],
            self.away[keep],
        )


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tag", help="the tag's id as the reader reports it (EPC hex); --sim: the walker's")
    p.add_argument(
        "--yaws-deg",
        default="50,-50",
        help="each antenna port's boresight yaw on the base, degrees CCW from forward, in port order "
        "(default 50,-50: port 1 front-left, port 2 front-right)",
    )
    p.add_argument("--sectors", type=int, default=16, help="bearing sectors of the table (default 16)")
    p.add_argument(
        "--ranges-m", default="0,1,2,3,4.5", help="range bin edges in metres (default 0,1,2,3,4.5)"
    )
    p.add_argument("--cycle-s", type=float, default=0.25, help="read cycle (default 0.25 s, as [following])")
    p.add_argument(
        "--seconds", type=float, default=6.0, help="robot: seconds of reads per station (default 6)"
    )
    p.add_argument("--walk-speed", type=float, default=0.7, help="--sim: walking speed, m/s (default 0.7)")
    p.add_argument(
        "--facing",
        choices=("away", "both"),
        default="both",
        help="fit on all cycles (both, the default) or only on those with the person's back to the robot, "
        "as a follower sees them (away: their body between the tag and the antennas lowers the RSSI)",
    )


def interactive(ctx: StepContext, options: argparse.Namespace) -> argparse.Namespace:
    if ctx.sim is None and not options.tag:
        options.tag = ask_line(ctx.console, "the tag's id (EPC hex, as `vlp-agent devices` shows it)").strip()
    return options


def _numbers(text: str, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError as exc:
        raise CalibrationError(f"{what}: not a comma-separated list of numbers: {text!r}") from exc
    if not values or not all(math.isfinite(v) for v in values):
        raise CalibrationError(f"{what}: give at least one finite number, got {text!r}")
    return values


# -- the scripted walk (simulation) --------------------------------------------------------------------------
def _crosses(a: tuple[float, float], b: tuple[float, float], walls: tuple[object, ...]) -> bool:
    from drivers.sim.raycast import walls_array

    seg = walls_array(walls)
    if not seg.size:
        return False
    d = np.subtract(b, a)
    e = seg[:, 2:] - seg[:, :2]
    w = seg[:, :2] - np.asarray(a)
    denom = d[0] * e[:, 1] - d[1] * e[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0]) / denom
        u = (w[:, 0] * d[1] - w[:, 1] * d[0]) / denom
    return bool(np.any((np.abs(denom) > 1e-12) & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)))


def walk_path(
    world: World, radii_m: tuple[float, ...], clearance_m: float = 0.3
) -> tuple[tuple[float, float], ...]:
    """Circles round the robot's start at ``radii_m``, each kept only when it stays ``clearance_m`` clear
    of every wall, joined by radial steps: the walker's path (walked once). A circle of radius r is
    walked ceil(3 m / r) times, so that the short inner ones give every sector a few read cycles too; then
    spokes out and back every 22.5 degrees between the innermost and outermost circles."""
    x0, y0 = world.robot.start.x_m, world.robot.start.y_m
    path: list[tuple[float, float]] = []
    for r in radii_m:
        ring = [
            (x0 + r * math.cos(2 * math.pi * k / 24), y0 + r * math.sin(2 * math.pi * k / 24))
            for k in range(25)
        ]
        wider = [
            (
                x0 + (r + clearance_m) * math.cos(2 * math.pi * k / 24),
                y0 + (r + clearance_m) * math.sin(2 * math.pi * k / 24),
            )
            for k in range(25)
        ]
        legs = [*itertools.pairwise(wider), *itertools.pairwise(ring)]
        if any(_crosses(a, b, world.walls) for a, b in legs):
            continue
        if path and _crosses(path[-1], ring[0], world.walls):
            continue
        laps = max(1, math.ceil(3.0 / r))
        path += ring[:-1] * laps + ring[-1:]
    kept = [r for r in radii_m if any(math.isclose(math.dist(p, (x0, y0)), r) for p in path)]
    if len(kept) >= 2:
        # Spokes: out and back every 22.5 degrees between the innermost and outermost circle kept, so the
        # walker is seen walking away (their body between the tag and the robot) and towards the robot.
        r0, r1 = min(kept), max(kept)
        for k in range(16):
            a = 2 * math.pi * k / 16
            inner = (x0 + r0 * math.cos(a), y0 + r0 * math.sin(a))
            outer = (x0 + r1 * math.cos(a), y0 + r1 * math.sin(a))
            if _crosses(path[-1], inner, world.walls) or _crosses(inner, outer, world.walls):
                continue
            path += [inner, outer, inner]
    return tuple(path)


def record_sim_walk(
    world: World,
    tag_id: str,
    ports: tuple[int, ...],
    cycle_s: float,
    speed_mps: float,
    seed: int,
    radii_m: tuple[float, ...],
) -> tuple[Recording, float]:
    """The scripted walk of ``--sim``: returns the recording and the walk's length in metres."""
    from drivers.fakes.rfid import wire_tag_id
    from drivers.sim.rfid_cycles import read_cycles

    path = walk_path(world, radii_m)
    if len(path) < 2:
        raise CalibrationError(
            f"world {world.name!r}: no circle round the robot's start clears the walls; start it in a room"
        )
    walker = Person("rfid-walker", tag_id, path, speed_mps=speed_mps, yields=False, loop=False)
    walk = dataclasses.replace(world, people=(walker,))
    length = sum(math.dist(a, b) for a, b in itertools.pairwise(path))
    wire = wire_tag_id(tag_id, "mercury")
    rows: list[Row] = []
    last_range = None
    for cycle in read_cycles(walk, duration_s=length / speed_mps, cycle_s=cycle_s, ports=ports, seed=seed):
        obs = observation_from_reads(cycle.reads, ports, wire)
        truth = cycle.truth[walker.name]
        # Walking away (their back to the robot): the range grew over the cycle.
        away = last_range is not None and truth.range_m - last_range > 0.3 * speed_mps * cycle_s
        rows.append((truth.bearing_rad, truth.range_m, obs.detected, obs.rssi_dbm, away))
        last_range = truth.range_m
    return _recording(rows), length


Row = tuple[float, float, npt.NDArray[np.bool_], FloatArray, bool]


def _recording(rows: list[Row]) -> Recording:
    return Recording(
        np.array([r[0] for r in rows]),
        np.array([r[1] for r in rows]),
        np.array([r[2] for r in rows], dtype=np.bool_),
        np.array([r[3] for r in rows], dtype=np.float64),
        np.array([r[4] for r in rows], dtype=np.bool_),
    )


# -- the stations (robot) ------------------------------------------------------------------------------------
def _record_stations(
    ctx: StepContext,
    tag_id: str,
    ports: tuple[int, ...],
    cycle_s: float,
    seconds: float,
    ranges: tuple[float, ...],
) -> Recording:
    rig = Rig.for_context(ctx)
    rows: list[Row] = []
    with rig:
        reader = rig.rfid()
        for r in ranges:
            for k in range(8):
                bearing = math.radians(45.0 * k)
                for away, facing in ((False, "facing the robot"), (True, "with your back to the robot")):
                    ask_line(
                        ctx.console,
                        f"stand at {math.degrees(math.remainder(bearing, math.tau)):+.0f} deg, {r:g} m, "
                        f"{facing}; press Enter",
                    )
                    reader.drain()
                    end = time.monotonic() + seconds
                    while time.monotonic() < end:
                        window_end = time.monotonic() + cycle_s
                        reads = []
                        while (left := window_end - time.monotonic()) > 0:
                            read = reader.read(timeout_s=left)
                            if read is not None:
                                reads.append(read)
                        obs = observation_from_reads(reads, ports, tag_id)
                        rows.append((math.remainder(bearing, math.tau), r, obs.detected, obs.rssi_dbm, away))
                    ctx.console.status(f"  {len(rows)} cycles")
    return _recording(rows)


# -- the step ------------------------------------------------------------------------------------------------
def run(ctx: StepContext, options: argparse.Namespace) -> StepResult:
    console = ctx.console
    yaws = tuple(math.radians(v) for v in _numbers(options.yaws_deg, "--yaws-deg"))
    edges = _numbers(options.ranges_m, "--ranges-m")
    try:
        grid = SectorGrid(options.sectors, edges)
    except ValueError as exc:
        raise CalibrationError(f"--sectors/--ranges-m: {exc}") from exc
    if not 0.05 <= options.cycle_s <= 5.0:
        raise CalibrationError("--cycle-s must be 0.05-5 s")
    ports = tuple(range(1, len(yaws) + 1))
    model = RadioModel(tuple(Antenna(p, y) for p, y in zip(ports, yaws, strict=True)))
    prior = default_table(model, grid)
    output = ctx.output(options.output, DEFAULT_FILE)
    ranges = tuple((a + b) / 2.0 for a, b in itertools.pairwise(edges))
    if ctx.sim is not None:
        world = ctx.sim.load()
        rf = world.rfid
        if rf.protocol != "mercury" or not rf.antenna_yaws_rad:
            raise CalibrationError(
                f"world {world.name!r}: its reader has no antennas to calibrate; give [rfid] protocol = "
                '"mercury" and antenna_yaws_deg (docs/world.md)'
            )
        if len(rf.antenna_yaws_rad) != len(yaws):
            raise CalibrationError(
                f"--yaws-deg names {len(yaws)} antennas, the world's reader has {len(rf.antenna_yaws_rad)}"
            )
        if not 0.2 <= options.walk_speed <= 2.0:
            raise CalibrationError("--walk-speed must be 0.2-2 m/s")
        tag = options.tag or "E20000000000000000000001"
        radii = tuple(r for r in ranges if r <= rf.range_m)
        at = ", ".join(f"{r:g}" for r in radii)
        console.say(f"rfid: a person walks circles round the simulated robot in {world.name!r} at {at} m")
        recording, length = record_sim_walk(
            world, tag, ports, options.cycle_s, options.walk_speed, ctx.sim.seed, radii
        )
        console.say(f"  {length:.0f} m walked, {len(recording.range_m)} read cycles")
    else:
        ctx.require_robot("the RFID calibration")
        if not options.tag:
            raise CalibrationError("give the tag's id: --tag EPC (as the reader reports it)")
        if not 1.0 <= options.seconds <= 60.0:
            raise CalibrationError("--seconds must be 1-60")
        console.say("rfid: mark 8 directions (every 45 deg, 0 = straight ahead, + = left) at each distance")
        recording = _record_stations(
            ctx, options.tag.upper(), ports, options.cycle_s, options.seconds, ranges
        )
    used = recording.subset(recording.away) if options.facing == "away" else recording
    console.say(f"  fitting on {len(used.range_m)} cycles ({options.facing})")
    table, counts = fit_table(prior, used.bearing_rad, used.range_m, used.detected, used.rssi_dbm)
    return _result(table, prior, counts, used, output)


def left_right_correlation(recording: Recording) -> float:
    """corr(RSSI port 1 - RSSI port 2, sin(bearing)) over the cycles both ports read (NaN without two ports
    or fewer than 10 such cycles): eco.md §3's measure of the left/right cue."""
    if recording.detected.shape[1] < 2:
        return math.nan
    both = recording.detected[:, 0] & recording.detected[:, 1]
    diff = recording.rssi_dbm[both, 0] - recording.rssi_dbm[both, 1]
    ok = np.isfinite(diff)
    if np.count_nonzero(ok) < 10:
        return math.nan
    return float(np.corrcoef(diff[ok], np.sin(recording.bearing_rad[both][ok]))[0, 1])


def table_toml(table: LikelihoodTable, comments: list[str]) -> str:
    """The table file: top-level keys of :meth:`LikelihoodTable.to_dict` (``docs/following.md``)."""
    lines = [
        "# vlp-agent calibrate rfid: the RFID layer's likelihood table, for [following] rfid_table",
        *(f"# {c}" for c in comments),
        "",
    ]
    for key, value in table.to_dict().items():
        if isinstance(value, str):
            lines.append(f'{key} = "{value}"')
        elif isinstance(value, list) and value and isinstance(value[0], list):
            lines.append(f"{key} = [")
            for row in value:
                lines.append(f"    {row!r},")
            lines.append("]")
        else:
            lines.append(f"{key} = {value!r}")
    return "\n".join(lines) + "\n"


def _result(
    table: LikelihoodTable,
    prior: LikelihoodTable,
    counts: npt.NDArray[np.int64],
    recording: Recording,
    path: Path,
) -> StepResult:
    coverage = float(np.mean(counts >= MIN_CYCLES))
    corr = left_right_correlation(recording)
    read_rate = recording.detected.mean(axis=0) if len(recording.detected) else np.zeros(len(table.ports))
    shift = float(np.median(np.abs(table.rssi_mean_dbm - prior.rssi_mean_dbm)))
    checks = [Check(f"cells with at least {MIN_CYCLES} cycles", coverage, MIN_COVERAGE, "", at_least=True)]
    values = {
        "cycles": len(recording.range_m),
        "coverage": round(coverage, 3),
        "read_rate_per_port": [round(float(r), 3) for r in read_rate],
        "left_right_correlation": None if math.isnan(corr) else round(corr, 3),
        "median_change_from_model_db": round(shift, 2),
        "ports": list(table.ports),
        "sectors": table.grid.n_sectors,
        "range_edges_m": list(table.grid.range_edges_m),
    }
    report = [
        f"{values['cycles']} read cycles; {100 * coverage:.0f} % of the {counts.size} cells measured",
        "reads per cycle by port: "
        + ", ".join(f"{p}: {r:.2f}" for p, r in zip(table.ports, read_rate, strict=True)),
        f"left/right cue: corr(RSSI 1 - RSSI 2, sin bearing) = {corr:+.2f} (eco.md: 0.13-0.37 indoors while "
        "driving; the camera must decide)",
        f"the table moved {shift:.1f} dB (median) from the physical model",
    ]
    text = table_toml(table, report)
    both = recording.detected[:, 0] & recording.detected[:, 1] if recording.detected.shape[1] >= 2 else None
    panels = [plot.text_panel(report + [c.describe() for c in checks], title="RFID likelihood table")]
    if both is not None and np.any(both):
        pts = np.column_stack(
            (
                np.degrees(recording.bearing_rad[both]),
                recording.rssi_dbm[both, 0] - recording.rssi_dbm[both, 1],
            )
        )
        expected = table.rssi_mean_dbm[0].mean(axis=1) - table.rssi_mean_dbm[1].mean(axis=1)
        order = np.argsort(table.grid.bearings_rad)
        line = np.column_stack((np.degrees(table.grid.bearings_rad[order]), expected[order]))
        panels.insert(
            0,
            plot.scatter(
                [
                    plot.Series(pts, plot.BLUE, "a cycle's RSSI 1 - RSSI 2", 2),
                    plot.Series(line, plot.RED, "the table's mean difference", 2, line=True),
                ],
                title="left/right cue",
                axis_labels=("bearing (deg)", "dB"),
            ),
        )
    advice = [f'set [following] rfid_table = "{path}" in the robot config (docs/following.md)']
    if coverage < MIN_COVERAGE:
        advice.insert(0, "too few cells measured: walk (or stand) all round the robot at every distance")
    outputs = [Output(path, text), Output(path.with_suffix(".png"), plot.png(plot.grid(panels)), report=True)]
    return StepResult(NAME, values, checks, report, advice, outputs)
