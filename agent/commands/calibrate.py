"""``vlp-agent calibrate``: the calibration wizard (no STEP) or one step, scripted (``calibrate STEP``).

This module is the terminal: it prints, reads answers, turns Ctrl-C and SIGTERM into "step interrupted,
nothing written", and decides the exit code. The steps themselves are in the ``calibration`` package
(docs/calibration.md), which talks only through the console given here.

Exit codes: 0 done and saved; 1 the step could not run (bad input, no board, a device missing; nothing
written); 3 done, but the result failed its quality checks (only the PNG report saved, unless ``--force``);
130 interrupted (nothing written).
"""

from __future__ import annotations

import argparse
import shutil
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from types import FrameType
from typing import Any, TextIO

from agent.commands.args import dumps_json
from calibration.context import DEFAULT_SIM_WORLD, SimOptions, StepContext, default_output_dir
from calibration.files import check_writable, commit
from calibration.report import CalibrationError, StepResult
from calibration.steps import STEPS, StepInfo, load
from firmware_protocol.errors import VlpAgentError

EXIT_FAILED_CHECKS = 3
EXIT_INTERRUPTED = 130


def _add_common(p: argparse.ArgumentParser, *, in_step: bool) -> None:
    # In a step's parser the shared options default to "not given", so values given before the step name
    # (`calibrate --sim intrinsics`) are not overwritten by the step parser's defaults.
    def default(value: Any) -> Any:
        return argparse.SUPPRESS if in_step else value

    g = p.add_argument_group("where the robot is and where files go")
    g.add_argument("--sim", action="store_true", default=default(False), help="use the simulated robot")
    g.add_argument(
        "--world",
        metavar="FILE",
        default=default(None),
        help=f"the simulated robot's world (default: {DEFAULT_SIM_WORLD.name})",
    )
    g.add_argument("--seed", type=int, default=default(0), help="seed of the simulated robot (default: 0)")
    g.add_argument(
        "--config", metavar="FILE", default=default(None), help="the robot's config file (devices)"
    )
    g.add_argument(
        "--dir",
        metavar="DIR",
        default=default(None),
        help="folder for calibration files (default: "
        "/var/lib/vlp-agent/calibration when it exists, else ./vlp-calibration)",
    )
    g.add_argument(
        "--json", action="store_true", default=default(False), help="print the result as one JSON object"
    )
    g.add_argument(
        "--force",
        action="store_true",
        default=default(False),
        help="save the result even if it fails its checks",
    )


def add_parser(sub: Any, argv: Sequence[str] = ()) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "calibrate",
        # argparse would print "STEP ..." as if a step were required; without one the wizard runs.
        usage="%(prog)s [options] [STEP [step options]]",
        help="calibrate the robot: camera, mounts, LED survey, VLP error, laser, wheels, servos",
        description="Without STEP: the interactive calibration wizard (a menu of steps). With STEP: that "
        "step "
        "alone, scriptable. Every step also runs on the simulated robot (--sim). Files are saved atomically, "
        "keeping the previous version as NAME.bak. See docs/calibration.md.",
    )
    _add_common(p, in_step=False)
    steps = p.add_subparsers(dest="step", metavar="STEP")
    for info in STEPS:
        try:
            module = load(info)
        except ImportError as exc:
            steps.add_parser(info.name, help=f"(unavailable: {exc})")
            continue
        sp = steps.add_parser(info.name, help=info.title, description=f"{info.title}. Needs: {info.needs}.")
        _add_common(sp, in_step=True)
        sp.add_argument("--output", metavar="FILE", help=f"file to write (default: {info.writes} in --dir)")
        module.add_arguments(sp)


class TerminalConsole:
    """The console steps talk through. ``out`` gets the conversation (stderr under --json, so stdout holds
    only the JSON); on a terminal, status lines overwrite each other, elsewhere one per second at most."""

    def __init__(self, out: TextIO, live: bool) -> None:
        self.out = out
        self.live = live
        self._status_shown = False
        self._last_status = 0.0

    def _clear(self) -> None:
        if self._status_shown:
            self.out.write("\r\x1b[K")
            self._status_shown = False

    def say(self, text: str = "") -> None:
        self._clear()
        print(text, file=self.out, flush=True)

    def status(self, text: str) -> None:
        if self.live:
            width = shutil.get_terminal_size((120, 20)).columns - 1
            self.out.write("\r\x1b[K" + text[:width])
            self.out.flush()
            self._status_shown = bool(text)
        elif text and time.monotonic() - self._last_status >= 1.0:
            self._last_status = time.monotonic()
            print(text, file=self.out, flush=True)

    def ask(self, question: str) -> str:
        self._clear()
        self.out.write(question)
        self.out.flush()
        line = sys.stdin.readline()
        if not line:
            raise EOFError
        return line.rstrip("\r\n")


def _context(args: argparse.Namespace, console: TerminalConsole, interactive: bool) -> StepContext:
    sim = None
    if getattr(args, "sim", False) or getattr(args, "world", None):
        world = Path(args.world) if getattr(args, "world", None) else DEFAULT_SIM_WORLD
        sim = SimOptions(world, getattr(args, "seed", 0))
    config = Path(args.config) if getattr(args, "config", None) else None
    if sim is not None and config is not None:
        raise CalibrationError("give --sim (the simulated robot) or --config (a real robot), not both")
    out_dir = Path(args.dir) if getattr(args, "dir", None) else default_output_dir()
    return StepContext(console, out_dir, sim, config, interactive)


def _on_sigterm(signum: int, frame: FrameType | None) -> None:
    # A service manager stopping us mid-step: unwind as Ctrl-C does (wheels stopped, nothing written).
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    signal.signal(signal.SIGTERM, _on_sigterm)
    as_json = bool(getattr(args, "json", False))
    out = sys.stderr if as_json else sys.stdout
    console = TerminalConsole(out, live=out.isatty())
    if args.step is None:
        if as_json:
            print("vlp-agent calibrate: --json needs a STEP (the wizard is interactive)", file=sys.stderr)
            return 2
        from calibration.wizard import Wizard

        try:
            ctx = _context(args, console, interactive=True)
        except CalibrationError as exc:
            print(f"vlp-agent calibrate: {exc}", file=sys.stderr)
            return 1
        return Wizard(ctx, force=bool(getattr(args, "force", False))).run()
    return _run_step(args, console, as_json)


def _run_step(args: argparse.Namespace, console: TerminalConsole, as_json: bool) -> int:
    info: StepInfo = next(s for s in STEPS if s.name == args.step)
    try:
        ctx = _context(args, console, interactive=False)
        module = load(info)
        check_writable(ctx.output(getattr(args, "output", None), info.writes).parent)
        result: StepResult = module.run(ctx, args)
        commit(result, force=bool(getattr(args, "force", False)))
    except VlpAgentError as exc:
        console.status("")
        print(f"vlp-agent calibrate {info.name}: {exc}", file=sys.stderr)
        print("  no calibration file was written", file=sys.stderr)
        return 1
    except EOFError:
        # Every question goes through calibration.report's ask helpers, which say which question had no
        # answer; this is the net under a question that does not.
        console.status("")
        print(f"vlp-agent calibrate {info.name}: end of input (stdin is closed)", file=sys.stderr)
        print("  no calibration file was written", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        console.status("")
        print(
            f"\nvlp-agent calibrate {info.name}: interrupted; no calibration file was written (previous "
            "files kept)",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    if as_json:
        print(dumps_json(result.as_json(), sort_keys=True))
    else:
        for line in result.text():
            console.say(line)
    return 0 if result.ok else EXIT_FAILED_CHECKS
