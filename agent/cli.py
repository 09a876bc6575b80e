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

# The agent's latency comes from many small array operations, not big ones: a thread pool per library only
# adds wake-ups and contention on a 2-4 core robot computer (measured: one VLP step 100x slower under load
# with threaded BLAS). Set before numpy or OpenCV is first imported; a user's explicit setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from agent import __version__  # noqa: E402
from agent.commands.args import UsageError, verbosity_parent  # noqa: E402
from firmware_protocol.errors import VlpAgentError  # noqa: E402

# Subcommand name -> module in agent.commands, imported only when used so `--help` stays fast.
COMMANDS: dict[str, str] = {
    "run": "agent.commands.run",
    "sim": "agent.commands.sim",
    "devices": "agent.commands.devices",
    "fake": "agent.commands.fake",
    "eval": "agent.commands.eval",
    "calibrate": "agent.commands.calibrate",
    "replay": "agent.commands.replay",
    "export": "agent.commands.export",
    "bridge": "agent.commands.bridge",
    "fleet": "agent.commands.fleet",
}

log = logging.getLogger("vlp_agent")


SYSLOG_PRIORITY = {
    logging.DEBUG: 7,
    logging.INFO: 6,
    logging.WARNING: 4,
    logging.ERROR: 3,
    logging.CRITICAL: 2,
}


class JournalFormatter(logging.Formatter):
    """Under systemd, stderr goes to the journal, which stamps time itself and reads a ``<N>`` syslog
    priority prefix: give it that instead of our own timestamp."""

    def format(self, record: logging.LogRecord) -> str:
        priority = SYSLOG_PRIORITY.get(record.levelno, 6)
        return f"<{priority}>{record.name}: {super().format(record)}"


def configure_logging(level: int) -> None:
    handler = logging.StreamHandler(sys.stderr)
    if os.environ.get("JOURNAL_STREAM"):
        handler.setFormatter(JournalFormatter("%(message)s"))
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=level, handlers=[handler])


def chosen_command(argv: Sequence[str], names: Sequence[str]) -> tuple[str | None, list[str]]:
    """The subcommand ``argv`` names (its first positional token, when it is one of ``names``) and the
    tokens after it; (None, []) otherwise. The options before a command (``-v``, ``--version``,
    ``--help``) take no value, so the first token not starting with ``-`` is the command."""
    for i, token in enumerate(argv):
        if not token.startswith("-"):
            return (token, list(argv[i + 1 :])) if token in names else (None, [])
    return None, []


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The command line's parser. With ``argv`` naming a command, only that command's module is imported
    (its parser holds everything it needs); the others get bare entries. Each command brings its own
    libraries (the VLP pipeline, SLAM, the simulator), and a process that runs one of them should carry
    only its memory (``vlp-agent eval slam`` on a large building is near the 250 MB budget)."""
    parser = argparse.ArgumentParser(
        prog="vlp-agent",
        description="On-board localization for indoor mobile robots: visible light positioning from ceiling "
        "LEDs and laser SLAM, driving the camera, laser, servos, IMU and RFID reader directly. "
        "With no hardware, everything runs on the simulated robot.",
    )
    parser.add_argument("--version", action="version", version=f"vlp-agent {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    chosen, rest = chosen_command(sys.argv[1:] if argv is None else argv, list(COMMANDS))
    for name, module_name in COMMANDS.items():
        if chosen is not None and name != chosen:
            sub.add_parser(name)
            continue
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            # One broken command must not take the others down: say why it is unavailable.
            sub.add_parser(name, help=f"(unavailable: {exc})")
            continue
        module.add_parser(sub, rest)
        _verbose_after_command(sub.choices[name])
    return parser


def _verbose_after_command(parser: argparse.ArgumentParser) -> None:
    """Let ``-v`` follow the command (``vlp-agent sim -v``, ``vlp-agent calibrate leds -v``) as well as
    precede it: the option is added to the command's parser and its nested ones (calibrate's steps). Its
    count goes to its own ``verbose_after`` field: a subparser fills a fresh namespace, which would
    otherwise overwrite the count given before the command."""
    if any("-v" in action.option_strings for action in parser._actions):
        return
    parent = verbosity_parent()
    for action in parent._actions:
        if "-v" in action.option_strings:
            parser._add_action(action)
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                _verbose_after_command(child)


def sub_parser(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    """The parser of command ``name`` (for its usage line)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and name in action.choices:
            chosen: argparse.ArgumentParser = action.choices[name]
            return chosen
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    verbose = args.verbose + getattr(args, "verbose_after", 0)
    configure_logging(logging.WARNING - 10 * min(verbose, 2))
    if "cv2" in sys.modules:
        # Same reason as the BLAS variables above: OpenCV's own pool, on by default, costs latency here.
        sys.modules["cv2"].setNumThreads(1)
    try:
        module = importlib.import_module(COMMANDS[args.command])
    except ImportError as exc:
        print(f"vlp-agent {args.command}: unavailable: {exc}", file=sys.stderr)
        return 1
    try:
        return int(module.run(args))
    except UsageError as exc:
        # Arguments that only make sense together, found wrong once all were read: a usage error, as
        # argparse reports one (usage line, exit status 2), not a failed run.
        command = sub_parser(parser, args.command)
        print(command.format_usage().rstrip(), file=sys.stderr)
        print(f"vlp-agent {args.command}: error: {exc}", file=sys.stderr)
        return 2
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
