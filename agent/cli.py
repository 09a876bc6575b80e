"""``vlp-agent``: a thin argparse front end with one subcommand per job.

Process concerns live here and only here: logging configuration, exit codes, and turning the project's
errors into one clear line instead of a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Sequence

from agent import __version__
from firmware_protocol.errors import VlpAgentError

# Subcommand name -> module in agent.commands, imported only when used so `--help` stays fast.
COMMANDS: dict[str, str] = {
    "sim": "agent.commands.sim",
    "devices": "agent.commands.devices",
    "fake": "agent.commands.fake",
}

log = logging.getLogger("vlp_agent")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vlp-agent",
        description="On-board localization for indoor mobile robots: visible light positioning from ceiling "
        "LEDs and laser SLAM, driving the camera, laser, servos, IMU and RFID reader directly. "
        "With no hardware, everything runs on the simulated robot.",
    )
    parser.add_argument("--version", action="version", version=f"vlp-agent {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module_name in COMMANDS.items():
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            # One broken command must not take the others down: say why it is unavailable.
            sub.add_parser(name, help=f"(unavailable: {exc})")
            continue
        module.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(
        level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr
    )
    try:
        module = importlib.import_module(COMMANDS[args.command])
    except ImportError as exc:
        print(f"vlp-agent {args.command}: unavailable: {exc}", file=sys.stderr)
        return 1
    try:
        return int(module.run(args))
    except VlpAgentError as exc:
        print(f"vlp-agent {args.command}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # Output piped into something that stopped reading (`| head`): not an error worth a traceback.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
