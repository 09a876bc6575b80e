"""``vlp-agent replay LOG``: re-run SLAM and the fusion on a recording, as fast as it goes, and compare.

LOG is a flight recording (MCAP, ``[recorder]`` / ``vlp-agent sim --record``: one file, or the name its
files were written under) or the fusion's JSON lines (``[record]`` / ``--record-fusion``). A fresh fusion
filter takes the recorded inputs in their order and every pose the agent wrote is compared with the
replayed estimate at the same input count (``max_pose_diff_m``). From a flight recording, a fresh SLAM
mapper built from ``/slam/setup`` takes the recorded raw scans with the odometry they went with, in the
order the live SLAM loop took them, and every filter update's pose is compared with the recorded one
(``max_slam_diff_m``; null when the recording has no SLAM inputs, with the reason under ``slam``). A cut or
corrupt file is read up to where it stops being readable, and the output says where (docs/recording.md).
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from agent.commands.args import dumps_json
from drivers.errors import ConfigError

log = logging.getLogger(__name__)


def add_parser(sub: Any, argv: Sequence[str] = ()) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "replay",
        help="re-run SLAM and the fusion on a recording and compare with the poses it holds",
        description=__doc__.split("\n\n", 1)[1].replace("``", "") if __doc__ else None,
    )
    p.add_argument("log", metavar="LOG", help="a flight recording (.mcap, or its name) or a JSON-lines one")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")


def run(args: argparse.Namespace) -> int:
    from agent.recording.reader import fusion_records, is_mcap, read_recordings
    from agent.recording.slam_replay import replay_slam
    from agent.runtime.recorder import read_recording, replay_records

    path = Path(args.log)
    out: dict[str, Any] = {"log": str(path)}
    if is_mcap(path):
        recordings = read_recordings(path)
        cut = next((r for r in recordings if r.stopped_at is not None), None)
        out["format"] = "mcap"
        out["files"] = [str(r.path) for r in recordings]
        out["messages"] = sum(len(r.messages) for r in recordings)
        out["complete"] = cut is None and all(r.complete for r in recordings)
        out["stopped"] = (
            None if cut is None else {"file": str(cut.path), "at_byte": cut.stopped_at, "error": cut.error}
        )
        records = list(fusion_records(recordings))
        slam = replay_slam(recordings)
    elif path.exists():
        slam = "a JSON-lines recording holds the fusion's inputs only"
        records = list(read_recording(path))
        out["format"] = "jsonl"
        out["messages"] = len(records)
    else:
        raise ConfigError("LOG", f"{path}: no such recording")
    if not records or records[0].get("k") != "header":
        raise ConfigError("LOG", f"{path}: no fusion setup in it (another program's recording, or cut early)")
    result = replay_records(records)
    out.update(
        inputs=result.inputs,
        poses_compared=result.outputs,
        max_pose_diff_m=result.max_position_difference_m,
        max_yaw_diff_rad=result.max_yaw_difference_rad,
    )
    if isinstance(slam, str):
        out.update(max_slam_diff_m=None, slam=slam)
    else:
        out.update(
            max_slam_diff_m=slam.max_diff_m,
            max_slam_yaw_diff_rad=slam.max_yaw_diff_rad,
            slam={
                "mapper": slam.mapper,
                "restarts": slam.restarts,
                "scans": slam.scans,
                "fixes": slam.fixes,
                "scans_missing": slam.scans_missing,
                "poses": slam.poses,
                "poses_compared": slam.poses_compared,
                "poses_unmatched": slam.poses_unmatched,
                "steps_differing": slam.steps_differing,
            },
        )
    if args.json:
        print(dumps_json(out, sort_keys=True))
    else:
        for key, value in out.items():
            print(f"{key}: {value}")
    return 0
