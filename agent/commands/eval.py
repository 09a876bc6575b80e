"""``vlp-agent eval WHAT``: offline evaluations that run an algorithm on recorded or simulated data and
report speed and accuracy.

This module only dispatches: each evaluation is a module in ``EVALUATIONS`` with ``add_parser(subparsers)``
(adding its own sub-subcommand) and ``run(args) -> int``. Adding one is one line in the table.
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Sequence
from types import ModuleType
from typing import Any

# Evaluation name -> module; each module adds its own parser under `eval` and runs it.
EVALUATIONS: dict[str, str] = {
    "deliver": "agent.commands.eval_deliver",
    "explore": "agent.commands.eval_explore",
    "follow": "agent.commands.eval_follow",
    "nav": "agent.commands.eval_nav",
    "slam": "agent.commands.eval_slam",
    "track": "agent.commands.eval_track",
    "vlp": "agent.commands.eval_vlp",
}


def _module(name: str) -> ModuleType:
    return importlib.import_module(EVALUATIONS[name])


def add_parser(subparsers: Any, argv: Sequence[str] = ()) -> None:
    """The ``eval`` parser; with ``argv`` (the tokens after ``eval``) naming an evaluation, only that
    evaluation's module is imported (``eval slam`` does not load the VLP pipeline and the renderer)."""
    parser: argparse.ArgumentParser = subparsers.add_parser(
        "eval",
        help="evaluate an algorithm offline on recorded or simulated data (speed, accuracy)",
        description="Run one of the agent's algorithms offline, as fast as it goes, on recorded or "
        "simulated data, and report its speed and accuracy.",
    )
    sub = parser.add_subparsers(dest="evaluation", metavar="WHAT")
    chosen = next((token for token in argv if not token.startswith("-")), None)
    for name in EVALUATIONS:
        if chosen in EVALUATIONS and name != chosen:
            sub.add_parser(name)
            continue
        try:
            module = _module(name)
        except ImportError as exc:
            sub.add_parser(name, help=f"(unavailable: {exc})")
            continue
        module.add_parser(sub)


def run(args: argparse.Namespace) -> int:
    name = getattr(args, "evaluation", None)
    if name is None:
        print("vlp-agent eval: say what to evaluate: " + ", ".join(EVALUATIONS))
        return 2
    return int(_module(name).run(args))
