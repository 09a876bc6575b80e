"""``vlp-agent export --ros2 LOG OUT``: a flight recording as a ROS 2 bag, for ``ros2 bag play`` and ROS.

LOG is a flight recording (MCAP, ``[recorder]`` / ``vlp-agent sim --record``: one file, or the name its
files were written under). OUT is the bag folder to make (rosbag2 with MCAP storage: OUT/OUT_0.mcap and
OUT/metadata.yaml); it must not exist or be empty. The bag holds standard message types: /scan
(sensor_msgs/msg/LaserScan), /odom (nav_msgs/msg/Odometry), /pose, /slam/pose and /vlp/pose
(geometry_msgs/msg/PoseWithCovarianceStamped), /map (nav_msgs/msg/OccupancyGrid), /tf and /tf_static
(tf2_msgs/msg/TFMessage: map -> base_link, base_link -> laser), /imu (sensor_msgs/msg/Imu), /cmd_vel
and /controller/cmd_vel (geometry_msgs/msg/TwistStamped: the velocity sent to the wheels, the
controller's velocity commands), /goal_pose (geometry_msgs/msg/PoseStamped: the controller's goals) and
/diagnostics (diagnostic_msgs/msg/DiagnosticArray: the devices' health), in Unix time. A cut or
corrupt recording is exported up to where it stops being readable, and the output says where
(docs/recording.md).
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
        "export",
        help="convert a flight recording to a ROS 2 bag (MCAP storage, standard message types)",
        description=__doc__.split("\n\n", 1)[1].replace("``", "") if __doc__ else None,
    )
    p.add_argument(
        "--ros2",
        action="store_true",
        required=True,
        help="write a ROS 2 bag (rosbag2, MCAP storage): the one export there is",
    )
    p.add_argument(
        "log", metavar="LOG", help="a flight recording (.mcap, or the name its files were written under)"
    )
    p.add_argument("out", metavar="OUT", help="the bag folder to make (must not exist, or be empty)")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")


def run(args: argparse.Namespace) -> int:
    from agent.recording.reader import is_mcap, read_recordings
    from agent.recording.ros2_export import export_ros2

    path = Path(args.log)
    if not is_mcap(path):
        raise ConfigError(
            "LOG", f"{path}: not a flight recording (no MCAP file there, nor {path.stem}-NNNN.mcap)"
        )
    recordings = read_recordings(path)
    cut = next((r for r in recordings if r.stopped_at is not None), None)
    try:
        result = export_ros2(recordings, Path(args.out))
    except FileExistsError as exc:
        raise ConfigError("OUT", str(exc)) from exc
    out: dict[str, Any] = {
        "log": str(path),
        "files": [str(r.path) for r in recordings],
        "messages": sum(len(r.messages) for r in recordings),
        "complete": cut is None and all(r.complete for r in recordings),
        "stopped": None
        if cut is None
        else {"file": str(cut.path), "at_byte": cut.stopped_at, "error": cut.error},
        "bag": str(result.bag),
        "bag_files": [str(p) for p in result.files],
        "topics": dict(sorted(result.counts.items())),
    }
    if args.json:
        print(dumps_json(out, sort_keys=True))
    else:
        for key, value in out.items():
            print(f"{key}: {value}")
    return 0
