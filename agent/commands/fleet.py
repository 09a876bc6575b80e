"""``vlp-agent fleet list``: the robots of the fleet, their poses and states, heard on Zenoh for a while.

Endpoints come from ``--connect`` / ``--listen`` or a bridge config (``--config``: its ``[zenoh]`` table).
docs/fleet.md.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from typing import Any

from agent.commands.args import UsageError, dumps_json, positive_seconds
from agent.fleet.bridge_config import ZenohConfig, load_bridge_config

__all__ = ["add_parser", "run"]


def add_parser(sub: Any, argv: Sequence[str] = ()) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "fleet",
        help="the fleet view: list the robots heard on Zenoh",
        description="Fleet commands on any machine that reaches the fleet's Zenoh network.",
    )
    fleet_sub = p.add_subparsers(dest="fleet_command", metavar="SUBCOMMAND", required=True)
    ls = fleet_sub.add_parser(
        "list",
        help="listen a few seconds and list the robots with pose and state",
        description="Subscribe to <prefix>/*/pose and <prefix>/*/status for --seconds and print each robot "
        "heard: its newest pose, its state (ready, starting, not-localized, agent-down) and how many poses "
        "came. Give the endpoints with --connect/--listen, or --config with a bridge config.",
    )
    ls.add_argument("--config", metavar="FILE", help="a bridge config: use its [zenoh] table and key_prefix")
    ls.add_argument(
        "--connect", metavar="ENDPOINT", action="append", default=[], help="e.g. tcp/10.0.0.5:7447"
    )
    ls.add_argument("--listen", metavar="ENDPOINT", action="append", default=[], help="e.g. tcp/0.0.0.0:7448")
    ls.add_argument("--scout", action="store_true", help="find peers by multicast scouting (off by default)")
    ls.add_argument("--prefix", default=None, help="key prefix (default: the config's, else 'fleet')")
    ls.add_argument("--seconds", type=positive_seconds, default=3.0, help="how long to listen (default: 3)")
    ls.add_argument("--json", action="store_true", help="print one JSON object")


def run(args: argparse.Namespace) -> int:
    from agent.fleet.view import FleetView

    prefix = "fleet"
    zenoh = ZenohConfig(
        mode="peer",
        listen=tuple(args.listen),
        connect=tuple(args.connect),
        multicast_scouting=args.scout,
    )
    if args.config:
        config = load_bridge_config(args.config)
        prefix = config.key_prefix
        if not (args.listen or args.connect):
            # The bridge's own listen endpoints would collide with the bridge: connect to them instead.
            z = config.zenoh
            zenoh = ZenohConfig("peer", (), z.connect + z.listen, z.multicast_scouting or args.scout)
    prefix = args.prefix or prefix
    if not (zenoh.listen or zenoh.connect or zenoh.multicast_scouting):
        raise UsageError("give --connect or --listen endpoints, --config, or --scout")
    view = FleetView(zenoh, prefix)
    robots = view.listen(args.seconds)
    if args.json:
        print(
            dumps_json({"robots": [r.as_dict() for r in robots], "rejected": view.rejected}, sort_keys=True)
        )
        return 0
    if not robots:
        print(f"no robot heard under {prefix}/* in {args.seconds:g} s")
    for r in robots:
        p = r.pose
        where = "no pose" if p is None else f"({p.x_m:.3f}, {p.y_m:.3f}) m {math.degrees(p.yaw_rad):.1f} deg"
        state = r.status.state if r.status is not None else "unknown"
        print(f"{r.robot:<16} {state:<14} {where}  [{r.poses} poses]")
    if view.rejected:
        print(f"{view.rejected} malformed messages ignored")
    return 0
