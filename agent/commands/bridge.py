"""``vlp-agent bridge --config FILE``: the fleet bridge process, the agent's Unix socket <-> Zenoh.

Runs until SIGTERM or Ctrl-C, then prints its counters (``--json``: one JSON object). ``--print-unit``
prints the systemd drop-in that allows the bridge's unit to reach its configured endpoints and exits.
docs/fleet.md.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Sequence
from typing import Any

from agent.commands.args import UsageError, dumps_json
from agent.fleet.bridge_config import load_bridge_config

__all__ = ["add_parser", "run"]

_SIGNALS = (signal.SIGTERM, signal.SIGINT)


def add_parser(sub: Any, argv: Sequence[str] = ()) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "bridge",
        help="the fleet bridge: this robot's agent <-> the fleet over Zenoh",
        description="Connect to the local agent's fleet socket ([fleet] socket in its config) and to the "
        "fleet over Zenoh (peer mode, explicit endpoints, multicast scouting off unless configured). "
        "Publishes <prefix>/<robot>/pose, /status and /goal_state; hands the other robots' poses and this "
        "robot's goals to the agent. Malformed network messages are counted and dropped. Runs until "
        "SIGTERM or Ctrl-C, then prints its counters. The config file is described in docs/fleet.md.",
    )
    p.add_argument("--config", metavar="FILE", required=True, help="bridge config (TOML, docs/fleet.md)")
    p.add_argument("--json", action="store_true", help="print the counters at exit as one JSON object")
    p.add_argument(
        "--print-unit",
        action="store_true",
        help="print the systemd drop-in for vlp-agent-bridge.service (IPAddressAllow= the config's "
        "endpoints, which must be IP addresses) and exit; install it as "
        "/etc/systemd/system/vlp-agent-bridge.service.d/endpoints.conf",
    )
    p.add_argument(
        "--allow",
        metavar="ADDRESS",
        action="append",
        default=[],
        help="with --print-unit: one more address or prefix to allow (a peer that only connects to this "
        "bridge's listen endpoint), e.g. 10.0.0.0/24",
    )


def run(args: argparse.Namespace) -> int:
    from agent.fleet.bridge import Bridge

    config = load_bridge_config(args.config)
    if args.print_unit:
        from agent.fleet.unit import drop_in

        print(drop_in(config.zenoh, args.config, args.allow), end="")
        return 0
    if args.allow:
        raise UsageError("--allow goes with --print-unit")
    bridge = Bridge(config)
    stop = threading.Event()
    failure: list[BaseException] = []

    def body() -> None:
        try:
            bridge.run(stop)
        except Exception as exc:  # reported by the main thread: a session that cannot open, say
            failure.append(exc)

    # Its own two signal handlers, not agent.runtime.shutdown: importing agent.runtime loads the whole agent
    # (1.2 s of imports on the development machine), and a restarted bridge should be back within 2 s.
    previous = {sig: signal.signal(sig, lambda signum, frame: stop.set()) for sig in _SIGNALS}
    try:
        thread = threading.Thread(target=body, name="bridge", daemon=True)
        thread.start()
        print(f"bridge {config.robot}: agent {config.socket}; Ctrl-C to stop", file=sys.stderr, flush=True)
        while not stop.is_set() and thread.is_alive():
            thread.join(0.2)
        stop.set()
        thread.join(5.0)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    counts = bridge.counters()
    if args.json:
        print(
            dumps_json(
                {"robot": config.robot, "counters": counts, "error": str(failure[0]) if failure else None}
            )
        )
    else:
        for name in sorted(counts):
            print(f"{name}: {counts[name]}")
    if failure:
        print(f"vlp-agent bridge: {failure[0]}", file=sys.stderr)
        return 1
    return 0
