"""What the commands share on the command line: argument types that refuse nonsense as usage errors, the
options every command takes, and the one way JSON goes out.

A bad value found by argparse ends the process with exit status 2 and the usage; a bad combination found
only once several arguments are known raises :class:`UsageError`, which ``agent.cli`` reports the same way.
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

__all__ = ["UsageError", "dumps_json", "positive_seconds", "verbosity_parent"]


class UsageError(Exception):
    """Arguments that parse one by one but do not make sense together (exit status 2, as argparse's)."""


def positive_seconds(text: str) -> float:
    """A duration in seconds: a finite number above zero. ``0``, ``-1``, ``nan`` and ``inf`` would start a
    run that ends at once (or never) and still write its files, so they are refused up front."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not math.isfinite(value) or value <= 0.0:
        raise argparse.ArgumentTypeError(f"{text!r}: must be a finite number of seconds above 0")
    return value


def verbosity_parent() -> argparse.ArgumentParser:
    """``-v`` for a subcommand's parser, so it works after the command name as well as before it. The
    count goes to ``verbose_after`` (added to the count given before the command); its default is suppressed
    so that a nested command's parser does not reset it."""
    parent = argparse.ArgumentParser(add_help=False)
    parent.add_argument(
        "-v",
        "--verbose",
        dest="verbose_after",
        action="count",
        default=argparse.SUPPRESS,
        help="more log output (-vv: debug)",
    )
    return parent


def _strict(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (JSON null), through dicts, lists and tuples;
    numpy scalars and arrays become Python numbers and lists (duck-typed: numpy is not imported for this)."""
    if type(value).__module__ == "numpy" and hasattr(value, "tolist"):
        value = value.tolist()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _strict(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_strict(v) for v in value]
    return value


def dumps_json(value: Any, **kwargs: Any) -> str:
    """JSON that strict parsers accept: NaN and infinities, which ``json.dumps`` writes as the non-standard
    ``NaN``/``Infinity`` tokens, become null (no value), and anything left over raises instead."""
    return json.dumps(_strict(value), allow_nan=False, **kwargs)
