"""``vlp-agent fleet list`` / ``fleet goal`` / ``fleet map`` / ``fleet router``: the robots of the fleet,
their poses and states, heard on Zenoh for a while; a goal sent to one robot, and its statuses; every
robot's map merged into one picture; a Zenoh router for the bridges to meet at.

Endpoints come from ``--connect`` / ``--listen`` or a bridge config (``--config``: its ``[zenoh]`` table).
docs/fleet.md.
"""

from __future__ import annotations

import argparse
import math
import secrets
from collections.abc import Sequence
from typing import Any

from agent.commands.args import UsageError, dumps_json, positive_seconds
from agent.fleet.bridge_config import ZenohConfig, load_bridge_config

__all__ = ["add_parser", "run"]


def _endpoint_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE", help="a bridge config: use its [zenoh] table and key_prefix")
    p.add_argument(
        "--connect", metavar="ENDPOINT", action="append", default=[], help="e.g. tcp/10.0.0.5:7447"
    )
    p.add_argument("--listen", metavar="ENDPOINT", action="append", default=[], help="e.g. tcp/0.0.0.0:7448")
    p.add_argument("--scout", action="store_true", help="find peers by multicast scouting (off by default)")
    p.add_argument("--prefix", default=None, help="key prefix (default: the config's, else 'fleet')")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def add_parser(sub: Any, argv: Sequence[str] = ()) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "fleet",
        help="the fleet view: list the robots heard on Zenoh, send one a goal, merge their maps; a router",
        description="Fleet commands on any machine that reaches the fleet's Zenoh network.",
    )
    fleet_sub = p.add_subparsers(dest="fleet_command", metavar="SUBCOMMAND", required=True)
    ls = fleet_sub.add_parser(
        "list",
        help="listen a few seconds and list the robots with pose and state",
        description="Subscribe to <prefix>/*/pose and <prefix>/*/status for --seconds and print each robot "
        "heard: its newest pose, its state (ready, starting, not-localized, agent-down; 'gone' when nothing "
        "came from it for --stale-s) and how many poses came. Give the endpoints with --connect/--listen, "
        "or --config with a bridge config.",
    )
    _endpoint_args(ls)
    ls.add_argument("--seconds", type=positive_seconds, default=3.0, help="how long to listen (default: 3)")
    ls.add_argument(
        "--stale-s",
        type=positive_seconds,
        default=2.0,
        help="a robot heard from earlier but silent for this long is shown as gone (default: 2)",
    )
    goal = fleet_sub.add_parser(
        "goal",
        help="send a robot a goal and print its statuses",
        description="Publish a goal (map frame, metres) on <prefix>/ROBOT/goal once ROBOT's bridge "
        "subscribes there, and print the statuses its agent sends back on <prefix>/ROBOT/goal_state: the "
        "first one (accepted or rejected, with the reason), or with --wait every one until the goal is "
        "reached, failed, rejected or cancelled. The robot drives it only if its own controller drives "
        "nothing (docs/fleet.md, 'The goal flow'). Exit status 0: reached (with --wait) or accepted; 1: "
        "rejected, failed or cancelled; 3: nothing (or, with --wait, no end) heard within --timeout.",
    )
    goal.add_argument("robot", metavar="ROBOT", help="the robot's name (its bridge's [bridge] robot)")
    goal.add_argument("x", metavar="X", type=float, help="metres, map frame")
    goal.add_argument("y", metavar="Y", type=float, help="metres, map frame")
    goal.add_argument("--theta", type=float, default=None, metavar="DEG", help="final heading (default: any)")
    goal.add_argument("--goal-id", type=int, default=None, help="0..65535 (default: a random one)")
    goal.add_argument(
        "--allow-unknown",
        action="store_true",
        help="the way may cross space the robot's map does not know yet (a map being built)",
    )
    goal.add_argument("--wait", action="store_true", help="wait until the goal has ended")
    goal.add_argument(
        "--timeout", type=positive_seconds, default=None, help="seconds (default: 10, with --wait 300)"
    )
    _endpoint_args(goal)
    mp = fleet_sub.add_parser(
        "map",
        help="listen for every robot's map and write one merged map picture (PNG)",
        description="Subscribe to <prefix>/*/map, <prefix>/*/pose and <prefix>/*/topology for --seconds "
        "(robots send their map every 5 s even when it does not change), merge every robot's newest map in "
        "the shared map frame (a cell is occupied where any robot saw a wall, free where any saw free space "
        "and none a wall, unknown where nobody saw), and write a PNG with each robot's name at its pose and "
        "its recent path. --json prints, per pair of robots, the fraction of cells both saw that they "
        "classify alike and the shift between their walls there (docs/fleet.md, 'Maps'). Exit status 0: "
        "a map written; 3: no map heard.",
    )
    mp.add_argument("--out", metavar="PNG", required=True, help="where to write the merged map picture")
    mp.add_argument("--seconds", type=positive_seconds, default=6.0, help="how long to listen (default: 6)")
    mp.add_argument(
        "--topology-out", metavar="JSON", default=None, help="also write every robot's topological graph"
    )
    _endpoint_args(mp)
    rt = fleet_sub.add_parser(
        "router",
        help='run a Zenoh router where the bridges (mode = "client") meet',
        description="A Zenoh router in this process (eclipse-zenoh's, the same router as zenohd, no other "
        'install): the bridges of a fleet connect to it in client mode ([zenoh] mode = "client", '
        "connect = [its endpoint]) and reconnect on their own when it restarts. Scouting off. Runs until "
        "SIGTERM or Ctrl-C (or --seconds). Exit status 1: an endpoint could not be opened. "
        "docs/fleet.md, 'A router'.",
    )
    rt.add_argument(
        "--listen",
        metavar="ENDPOINT",
        action="append",
        required=True,
        help="where clients and peers reach it, e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    rt.add_argument(
        "--connect", metavar="ENDPOINT", action="append", default=[], help="another router (repeatable)"
    )
    rt.add_argument(
        "--seconds", type=positive_seconds, default=None, help="stop after this long (default: at a signal)"
    )
    rt.add_argument("--json", action="store_true", help="print one JSON object when it stops")


def _router(args: argparse.Namespace) -> int:
    import signal
    import sys
    import threading
    import time

    from agent.fleet.router import open_router
    from drivers.errors import DeviceNotFound

    stop = threading.Event()
    t0 = time.monotonic()
    error: str | None = None
    session: Any = None
    previous = {
        sig: signal.signal(sig, lambda signum, frame: stop.set()) for sig in (signal.SIGTERM, signal.SIGINT)
    }
    try:
        session = open_router(args.listen, args.connect)
        print(f"Zenoh router: listen {', '.join(args.listen)}; Ctrl-C to stop", file=sys.stderr, flush=True)
        stop.wait(args.seconds)
    except DeviceNotFound as exc:
        error = str(exc)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if session is not None:
            session.close()
    if args.json:
        out = {"listen": args.listen, "connect": args.connect, "seconds": round(time.monotonic() - t0, 3)}
        print(dumps_json({**out, "error": error}, sort_keys=True))
    if error is not None:
        print(f"vlp-agent fleet router: {error}", file=sys.stderr)
        return 1
    return 0


def _zenoh(args: argparse.Namespace) -> tuple[ZenohConfig, str]:
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
    return zenoh, prefix


def run(args: argparse.Namespace) -> int:
    if args.fleet_command == "goal":
        return _goal(args)
    if args.fleet_command == "map":
        return _map(args)
    if args.fleet_command == "router":
        return _router(args)
    from agent.fleet.view import FleetView

    zenoh, prefix = _zenoh(args)
    view = FleetView(zenoh, prefix, stale_s=args.stale_s)
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
        print(f"{r.robot:<16} {r.state:<14} {where}  [{r.poses} poses]")
    if view.rejected:
        print(f"{view.rejected} malformed messages ignored")
    return 0


def _goal(args: argparse.Namespace) -> int:
    from agent.fleet.goal_sender import GoalSender
    from agent.fleet.local_protocol import GoalMessage, valid_robot_name
    from firmware_protocol.command_frame import GoalReason, GoalState

    if not valid_robot_name(args.robot):
        raise UsageError(f"not a robot name: {args.robot!r} (1..32 of A-Z a-z 0-9 _ -)")
    if not (math.isfinite(args.x) and math.isfinite(args.y)) or (
        args.theta is not None and not math.isfinite(args.theta)
    ):
        raise UsageError("X, Y and --theta must be finite numbers")
    goal_id = secrets.randbelow(0x10000) if args.goal_id is None else args.goal_id
    if not 0 <= goal_id <= 0xFFFF:
        raise UsageError(f"--goal-id must be 0..65535, not {goal_id}")
    zenoh, prefix = _zenoh(args)
    yaw = math.nan if args.theta is None else math.radians(args.theta)
    timeout = args.timeout if args.timeout is not None else (300.0 if args.wait else 10.0)
    goal = GoalMessage(
        0, goal_id, args.x, args.y, yaw, GoalMessage.ALLOW_UNKNOWN if args.allow_unknown else 0
    )
    trace = GoalSender(zenoh, prefix).send(args.robot, goal, wait_end=args.wait, timeout_s=timeout)

    def named(state: Any) -> dict[str, Any]:
        return {
            "state": GoalState(state.state).name.lower(),
            "reason": GoalReason(state.reason).name.lower()
            if state.reason in GoalReason._value2member_map_
            else str(state.reason),
            "remaining_m": None if math.isnan(state.remaining_m) else state.remaining_m,
        }

    states = [named(s) for s in trace.states if s.state in GoalState._value2member_map_]
    last = trace.last
    if last is None:
        code = 3
    elif last.state == GoalState.REACHED or (
        not args.wait and last.state in (GoalState.ACCEPTED, GoalState.ACTIVE)
    ):
        code = 0
    elif last.state in (GoalState.ACCEPTED, GoalState.ACTIVE):
        code = 3  # --wait ran out
    else:
        code = 1
    if args.json:
        print(
            dumps_json(
                {
                    "robot": args.robot,
                    "goal_id": goal_id,
                    "sent": trace.sent,
                    "states": states,
                    "final": states[-1] if states else None,
                    "timed_out": code == 3,
                },
                sort_keys=True,
            )
        )
        return code
    if not trace.sent:
        print(f"no bridge of {args.robot} subscribes to {prefix}/{args.robot}/goal within {timeout:g} s")
        return 3
    for s in states:
        extra = "" if s["reason"] == "none" else f" ({s['reason']})"
        rest = "" if s["remaining_m"] is None else f", {s['remaining_m']:.2f} m to go"
        print(f"goal {goal_id} -> {args.robot}: {s['state']}{extra}{rest}")
    if code == 3:
        print(f"no {'end' if states else 'status'} heard within {timeout:g} s")
    return code


def _map(args: argparse.Namespace) -> int:
    import threading

    import zenoh as zenoh_lib

    from agent.fleet.map_view import FleetMaps, picture, report

    zenoh, prefix = _zenoh(args)
    collector = FleetMaps(prefix)
    session: Any = zenoh_lib.open(zenoh.zenoh_config())
    try:
        collector.subscribe(session)
        threading.Event().wait(args.seconds)
    finally:
        session.close()
    maps, poses, topologies = collector.snapshot()
    out = report(maps, poses)
    out["rejected"] = collector.rejected
    out["out"] = None
    if maps:
        import cv2

        if not cv2.imwrite(args.out, picture(maps, poses)):
            raise UsageError(f"--out {args.out}: cannot write a PNG there")
        out["out"] = args.out
    if args.topology_out and topologies:
        import json
        from pathlib import Path

        Path(args.topology_out).write_text(json.dumps(topologies, indent=1), encoding="utf-8")
    if args.json:
        print(dumps_json(out, sort_keys=True))
    elif not maps:
        print(f"no map heard under {prefix}/*/map in {args.seconds:g} s")
    else:
        print(f"merged map of {', '.join(sorted(maps))} -> {args.out}")
        for pair in out["pairs"]:
            a, b = pair["robots"]
            agree = pair["agreement"]
            shift = pair["shift_norm_m"]
            print(
                f"{a} / {b}: {pair['overlap_m2']} m2 seen by both, "
                f"{'-' if agree is None else f'{100 * agree:.1f} %'} alike, "
                f"walls shifted {'-' if shift is None else f'{100 * shift:.1f} cm'}"
            )
    return 0 if maps else 3
