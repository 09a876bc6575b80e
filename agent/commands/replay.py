"""``vlp-agent replay LOG``: re-run the fusion on a recording, as fast as it goes, and compare.

LOG is a flight recording (MCAP, ``[recorder]`` / ``vlp-agent sim --record``: one file, or the name its
files were written under) or the fusion's JSON lines (``[record]`` / ``--record-fusion``). A fresh filter
takes the recorded inputs in their order and every pose the agent wrote is compared with the replayed
estimate at the same input count (``agent.runtime.recorder.replay``). A cut or corrupt file is read up to
where it stops being readable, and the output says where. SLAM is not replayed yet (issue 21):
``max_slam_diff_m`` is null.
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
        help="re-run the fusion on a recording and compare with the poses written",
        description=__doc__.split("\n\n", 1)[1].replace("``", "") if __doc__ else None,
    )
    p.add_argument("log", metavar="LOG", help="a flight recording (.mcap, or its name) or a JSON-lines one")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")


def run(args: argparse.Namespace) -> int:
    from agent.recording.reader import fusion_records, is_mcap, read_recordings
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
    elif path.exists():
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
        max_slam_diff_m=None,  # SLAM replay is not there yet
    )
    if args.json:
        print(dumps_json(out, sort_keys=True))
    else:
        for key, value in out.items():
            print(f"{key}: {value}")
    return 0
