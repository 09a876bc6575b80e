"""Pose output cost: microseconds per pose to encode (pose frame, and MAVLink if pymavlink is installed) and
to decode a stream, and bytes per pose on the wire. Prints one JSON object.

    python benchmarks/pose_frame.py [--poses 20000]

The encode time sits on the latency-critical path (fused pose -> bytes on the serial line); the wire time
at a given baud is in ``docs/wire-format.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from firmware_protocol.mavlink_out import MavlinkEncodeError, MavlinkMessage, MavlinkPoseEncoder
from firmware_protocol.pose_frame import PoseFlags, PoseFrame, PoseFrameDecoder, encode_pose


def poses(n: int) -> list[PoseFrame]:
    rng = random.Random(0)
    return [
        PoseFrame(
            sequence=i,
            t_us=1_000_000 + 10_000 * i,
            x_m=rng.uniform(-20, 20),
            y_m=rng.uniform(-20, 20),
            yaw_rad=rng.uniform(-math.pi, math.pi),
            sigma_xy_m=rng.uniform(0.001, 0.05),
            sigma_yaw_rad=rng.uniform(0.001, 0.05),
            flags=PoseFlags.VLP | PoseFlags.SLAM | PoseFlags.ODOMETRY | PoseFlags.IMU,
            reset_counter=0,
        )
        for i in range(n)
    ]


def per_call_us(fn: Callable[[PoseFrame], bytes], items: list[PoseFrame]) -> dict[str, float]:
    """Median and p99 of single calls (what one pose costs), in microseconds."""
    times = []
    for p in items:
        t0 = time.perf_counter_ns()
        fn(p)
        times.append((time.perf_counter_ns() - t0) / 1000)
    times.sort()
    return {
        "median_us": round(statistics.median(times), 2),
        "p99_us": round(times[int(0.99 * len(times))], 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=20_000)
    args = parser.parse_args()
    items = poses(args.poses)
    result: dict[str, object] = {"poses": args.poses}

    result["pose_frame_encode"] = per_call_us(encode_pose, items)
    data = b"".join(encode_pose(p) for p in items)
    decoder = PoseFrameDecoder()
    t0 = time.perf_counter()
    decoded = decoder.feed(data)
    elapsed = time.perf_counter() - t0
    assert len(decoded) == args.poses
    result["pose_frame_decode_stream_us_per_pose"] = round(elapsed / args.poses * 1e6, 2)
    result["pose_frame_wire_bytes"] = len(data) // args.poses

    try:
        for kind in MavlinkMessage:
            encoder = MavlinkPoseEncoder(kind)
            result[f"mavlink_{kind.value}_encode"] = per_call_us(encoder.encode, items)
            result[f"mavlink_{kind.value}_wire_bytes"] = len(encoder.encode(items[0]))
    except MavlinkEncodeError as exc:  # pymavlink is not installed
        result["mavlink"] = f"skipped: {exc}"
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
