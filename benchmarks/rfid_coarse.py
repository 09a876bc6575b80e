"""Accuracy of the RFID coarse layer (``agent/following/coarse.py``) on simulated walks.

A room 9 x 7 m, a two-antenna Mercury reader (ports at +-50 degrees) on a standing robot, the channel
model of ``drivers/sim/rfid_channel.py``. The table is calibrated on one walk (circles round the robot,
``--calibration-seed``, as ``vlp-agent calibrate rfid --sim`` walks them) and the filter then tracks a
person walking a loop round the robot on other seeds (``--seeds``), with the physical model's table and
with the calibrated one. Prints one JSON object: per table the bearing error's median and p90 (degrees),
the share within 45 degrees, the mean reported confidence and the hit rate it should match (the truth
within one sector of the estimate), the mean probability of "ahead" while the person is ahead, the
probability of the forward camera's view (+-35 degrees) while they are in it and the bearing error of the
filter's answer within that view, the median range error (m) beside always answering the median range,
over all seeds; and the left/right correlation of the calibration walk.

    python benchmarks/rfid_coarse.py
    python benchmarks/rfid_coarse.py --seeds 2 3 4 5 --seconds 90
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agent.following.coarse import (
    Antenna,
    CoarseFilter,
    RadioModel,
    default_table,
    fit_table,
    observation_from_reads,
)
from calibration.rfid import left_right_correlation, record_sim_walk
from drivers.fakes.rfid import wire_tag_id
from drivers.sim.rfid_cycles import read_cycles
from drivers.sim.worldfile import load_world, parse_world

TAG = "E200001122334455"
HALF_FOV_RAD = math.radians(35.0)  # the default forward camera's half field of view
WORLD = f"""
name = "rfid-room"
[rfid]
protocol = "mercury"
range_m = 6.0
repeat_s = 0.1
antenna_yaws_deg = [50.0, -50.0]
[[rooms]]
x_min_m = -4.0
y_min_m = -3.5
x_max_m = 5.0
y_max_m = 3.5
[[people]]
name = "user"
tag_id = "{TAG}"
path = [[1.5, -1.5], [2.5, 0.0], [1.5, 1.5], [-1.5, 1.5], [-1.5, -1.5]]
speed_mps = 0.6
"""


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, nargs="+", default=[2, 3, 4])
    p.add_argument("--calibration-seed", type=int, default=11)
    p.add_argument("--seconds", type=float, default=60.0, help="simulated seconds of each walk (default 60)")
    p.add_argument(
        "--world",
        help="a world file instead of the room (e.g. examples/worlds/follow_straight.toml): calibrated round "
        "its robot's start, tracking its first person while they are within the grid's reach",
    )
    p.add_argument("--skip-cycles", type=int, default=20, help="read cycles left to converge (default 20)")
    p.add_argument("--likelihood-weight", type=float, default=None, help="the filter's (default: its own)")
    args = p.parse_args()
    world = parse_world(WORLD) if args.world is None else load_world(args.world)
    person = world.people[0]
    prior = default_table(RadioModel((Antenna(1, math.radians(50.0)), Antenna(2, math.radians(-50.0)))))
    radii = (0.5, 1.5, 2.5) if args.world is None else (0.5, 1.5, 2.5, 3.75)
    walk, _ = record_sim_walk(world, TAG, (1, 2), 0.25, 0.7, args.calibration_seed, radii)
    table, _ = fit_table(prior, walk.bearing_rad, walk.range_m, walk.detected, walk.rssi_dbm)
    wire = wire_tag_id(person.tag_id, "mercury")
    out: dict[str, object] = {
        "left_right_correlation": round(left_right_correlation(walk), 3),
        "seeds": args.seeds,
    }
    for name, t in (("model", prior), ("calibrated", table)):
        errors, confidence, hits, range_errors, ranges = [], [], [], [], []
        p_front, in_view, view_errors = [], [], []
        for seed in args.seeds:
            f = (
                CoarseFilter(t)
                if args.likelihood_weight is None
                else CoarseFilter(t, likelihood_weight=args.likelihood_weight)
            )
            for k, cycle in enumerate(read_cycles(world, duration_s=args.seconds, seed=seed)):
                f.predict(0.25)
                f.update(observation_from_reads(cycle.reads, t.ports, wire))
                if k < args.skip_cycles:
                    continue
                e = f.estimate()
                if cycle.truth[person.name].range_m >= t.grid.max_range_m:
                    continue  # beyond the grid: "absent" is the right answer there
                truth = cycle.truth[person.name].bearing_rad
                range_errors.append(abs(e.range_m - cycle.truth[person.name].range_m))
                ranges.append(cycle.truth[person.name].range_m)
                errors.append(abs(math.remainder(e.bearing_rad - truth, math.tau)))
                if abs(truth) < math.pi / 2:
                    p_front.append(e.p_front)
                if abs(truth) < HALF_FOV_RAD:
                    view = f.within(0.0, HALF_FOV_RAD)
                    in_view.append(view.probability)
                    if view.probability > 0:
                        view_errors.append(abs(math.remainder(view.bearing_rad - truth, math.tau)))
                confidence.append(e.confidence)
                centre = t.grid.bearings_rad[e.sector]
                hits.append(abs(math.remainder(truth - centre, math.tau)) <= 1.5 * t.grid.sector_width_rad)
        deg = np.degrees(errors)
        out[name] = {
            "cycles": len(errors),
            "error_deg_median": round(float(np.median(deg)), 1),
            "error_deg_p90": round(float(np.percentile(deg, 90)), 1),
            "within_45_deg": round(float(np.mean(deg < 45.0)), 3),
            "confidence_mean": round(float(np.mean(confidence)), 3),
            "hit_rate": round(float(np.mean(hits)), 3),
            # Front or back: the probability given to "ahead" when the person is ahead.
            "p_front_when_ahead_mean": round(float(np.mean(p_front)), 3) if p_front else None,
            # The forward camera's view (+-35 degrees): how likely the filter says the person is in it when
            # they are, and its bearing within the view.
            "in_view_probability_mean": round(float(np.mean(in_view)), 3) if in_view else None,
            "in_view_error_deg_median": round(float(np.degrees(np.median(view_errors))), 1)
            if view_errors
            else None,
            "range_error_m_median": round(float(np.median(range_errors)), 2),
            # The floor to beat: always answering the walk's median range.
            "range_error_m_median_constant": round(
                float(np.median(np.abs(np.subtract(ranges, np.median(ranges))))), 2
            ),
        }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
