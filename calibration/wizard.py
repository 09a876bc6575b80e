"""The interactive calibration wizard: a menu of the steps, each with what it needs and how it went.

Choosing a step asks its few questions (with defaults), runs it with live progress, shows the verdict with
the thresholds it used and what to do next, and saves its files (a result that fails its checks is saved only
if the user says so). Ctrl-C stops the running step, writes nothing, and comes back to the menu; at the menu
it
leaves the wizard.
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass

from calibration.context import StepContext
from calibration.files import check_writable, commit
from calibration.report import ask_yes
from calibration.steps import STEPS, StepInfo, load
from firmware_protocol.errors import VlpAgentError

__all__ = ["Wizard"]

log = logging.getLogger(__name__)

EXIT_INTERRUPTED = 130
# Input ended (stdin closed, or Ctrl-D) before the user said what to do: nothing was chosen, so not a success.
EXIT_NO_INPUT = 1


class _InputEnded(Exception):
    """The menu's question met the end of input."""


@dataclass
class _Done:
    verdict: str
    ok: bool


class Wizard:
    def __init__(self, ctx: StepContext, *, force: bool = False) -> None:
        self.ctx = ctx
        self.force = force
        self.done: dict[str, _Done] = {}

    def _where(self) -> str:
        ctx = self.ctx
        if ctx.sim is not None:
            return f"the simulated robot (world {ctx.sim.world_file.name}, seed {ctx.sim.seed})"
        if ctx.config is not None:
            return f"the robot in {ctx.config}"
        return (
            "no robot (pass --config FILE or --sim): only intrinsics and forward-camera from a folder of "
            "images can run"
        )

    def _status(self, step: StepInfo) -> str:
        if step.name in self.done:
            return self.done[step.name].verdict
        if (self.ctx.out_dir / step.writes).exists():
            return f"file from before: {step.writes}"
        return "not done"

    def _menu(self) -> str:
        say = self.ctx.console.say
        say("")
        say("vlp-agent calibration wizard")
        say(f"  robot: {self._where()}")
        say(f"  files: {self.ctx.out_dir}")
        say("")
        width = max(len(s.name) for s in STEPS)
        for n, step in enumerate(STEPS, start=1):
            say(f"  {f'{n}.':>3} {step.name:<{width}} {step.title}")
            say(f"      {'':<{width}} needs: {step.needs}")
            say(f"      {'':<{width}} status: {self._status(step)}")
        say("  q. quit")
        pending = [str(n) for n, s in enumerate(STEPS, start=1) if s.name not in self.done]
        default = pending[0] if pending else "q"
        names = {s.name: str(n) for n, s in enumerate(STEPS, start=1)}
        while True:
            try:
                answer = (
                    self.ctx.console.ask(f"step (1-{len(STEPS)}, a name, or q) [{default}]: ").strip().lower()
                )
            except EOFError:
                raise _InputEnded from None
            answer = answer or default
            if answer in ("q", "quit", "exit"):
                return "q"
            if answer.isdigit() and 1 <= int(answer) <= len(STEPS):
                return answer
            if answer in names:
                return names[answer]
            self.ctx.console.say(
                f"  {answer!r} is not a step: type a number from 1 to {len(STEPS)}, a step name, or q"
            )

    def run(self) -> int:
        console = self.ctx.console
        try:
            while True:
                choice = self._menu()
                if choice == "q":
                    console.say("calibration wizard: bye")
                    return 0
                self.run_step(STEPS[int(choice) - 1])
        except KeyboardInterrupt:
            console.say("")
            console.say("calibration wizard: interrupted at the menu; bye")
            return EXIT_INTERRUPTED
        except _InputEnded:
            console.say("")
            console.say(
                "calibration wizard: end of input (stdin is closed): the wizard needs someone to answer; "
                "for scripts, run one step: `vlp-agent calibrate STEP`"
            )
            return EXIT_NO_INPUT

    def _options(self, step: StepInfo) -> argparse.Namespace:
        module = load(step)
        parser = argparse.ArgumentParser(add_help=False)
        parser.add_argument("--output", default=None)
        module.add_arguments(parser)
        return parser.parse_args([])

    def run_step(self, step: StepInfo) -> None:
        console = self.ctx.console
        console.say("")
        console.say(f"== {step.name}: {step.title}")
        console.say(f"   needs: {step.needs}")
        try:
            module = load(step)
            options = self._options(step)
        except ImportError as exc:
            console.say(f"   unavailable: {exc}")
            self.done[step.name] = _Done("unavailable", False)
            return
        try:
            options = module.interactive(self.ctx, options)
            check_writable(self.ctx.out_dir)
            if not ask_yes(console, "start", True):
                return
            result = module.run(self.ctx, options)
            keep = result.ok or self.force
            if not keep:
                for line in result.text():
                    console.say(line)
                keep = ask_yes(console, "the result failed its checks; save it anyway", False)
            commit(result, force=keep)
        except KeyboardInterrupt:
            console.status("")
            console.say("")
            console.say(f"{step.name}: interrupted; no calibration file was written (previous files kept)")
            self.done[step.name] = _Done("interrupted", False)
            return
        except EOFError:
            # A question asked without ask_line/ask_*: the end of input still ends the step cleanly.
            console.status("")
            console.say(f"{step.name}: end of input (stdin is closed)")
            console.say("  no calibration file was written")
            self.done[step.name] = _Done("failed: end of input", False)
            return
        except VlpAgentError as exc:
            console.status("")
            console.say(f"{step.name}: {exc}")
            console.say("  no calibration file was written")
            self.done[step.name] = _Done("failed: " + str(exc).split(":")[0][:60], False)
            return
        for line in result.text():
            console.say(line)
        verdict = "GOOD" if result.ok else "NOT GOOD ENOUGH"
        saved = ", ".join(p.name for p in result.files) or "nothing saved"
        self.done[step.name] = _Done(f"done: {verdict} ({saved})", result.ok)
