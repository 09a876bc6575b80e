"""What a step gives back, how it is judged, and how it talks to the person running it.

A step returns a :class:`StepResult`: the numbers (the ``--json`` object), the :class:`Check` list that makes
the verdict (each with the threshold it used), report lines, what to do next, and the files it saved. Steps
never print: they talk through a :class:`Console` (the command module's terminal, or a test's script).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from firmware_protocol.errors import VlpAgentError

__all__ = [
    "CalibrationError",
    "Check",
    "Console",
    "Output",
    "StepResult",
    "ask_choice",
    "ask_float",
    "ask_int",
    "ask_line",
    "ask_yes",
]


class CalibrationError(VlpAgentError):
    """A step cannot give a result (no board found, too few views, a device missing, bad input). The
    message says what to do; nothing has been written."""


@dataclass(frozen=True, slots=True)
class Check:
    """One quality criterion: ``value`` against ``threshold`` (``value <= threshold`` passes, or ``>=``
    when ``at_least``)."""

    name: str
    value: float
    threshold: float
    unit: str = ""
    at_least: bool = False

    @property
    def ok(self) -> bool:
        if not math.isfinite(self.value):
            return False
        return self.value >= self.threshold if self.at_least else self.value <= self.threshold

    def describe(self) -> str:
        op = ">=" if self.at_least else "<="
        unit = f" {self.unit}" if self.unit else ""
        verdict = "ok" if self.ok else "NOT MET"
        return f"{self.name}: {_fmt(self.value)}{unit} (needs {op} {_fmt(self.threshold)}{unit}) {verdict}"

    def as_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "value": self.value if math.isfinite(self.value) else None,
            "threshold": self.threshold,
            "unit": self.unit,
            "at_least": self.at_least,
            "ok": self.ok,
        }


def _fmt(value: float) -> str:
    if not math.isfinite(value):
        return str(value)
    if value == int(value) and abs(value) < 1e6:
        return str(int(value))
    return f"{value:.3g}" if abs(value) < 0.01 else f"{value:.3f}".rstrip("0").rstrip(".")


@dataclass(frozen=True, slots=True)
class Output:
    """A file a step wants written. ``report`` files (the PNG) are saved even when the checks fail, so the
    user can see why; calibration files only when they pass (or the user insists)."""

    path: Path
    content: bytes | str
    report: bool = False


@dataclass
class StepResult:
    """A finished step. ``values`` is what ``--json`` prints (plus ``ok``, ``checks`` and ``files``).
    ``outputs`` are the files to write; ``files`` the ones written (set when they are saved)."""

    step: str
    values: dict[str, Any]
    checks: list[Check] = field(default_factory=list)
    report: list[str] = field(default_factory=list)
    advice: list[str] = field(default_factory=list)
    outputs: list[Output] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)
    withheld: list[Path] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return all(check.ok for check in self.checks)

    def verdict(self) -> str:
        if not self.checks:
            return "done"
        failed = [c.name for c in self.checks if not c.ok]
        return "GOOD: every check passed" if not failed else "NOT GOOD ENOUGH: " + ", ".join(failed)

    def as_json(self) -> dict[str, Any]:
        out = dict(self.values)
        out["step"] = self.step
        out["ok"] = self.ok
        out["checks"] = [c.as_json() for c in self.checks]
        out["files"] = [str(p) for p in self.files]
        out["not_saved"] = [str(p) for p in self.withheld]
        return out

    def text(self) -> list[str]:
        lines = [f"{self.step}: {self.verdict()}"]
        lines += [f"  {line}" for line in self.report]
        if self.checks:
            lines.append("  checks:")
            lines += [f"    {c.describe()}" for c in self.checks]
        if self.files:
            lines.append("  saved:")
            lines += [f"    {p}" for p in self.files]
        if self.withheld:
            lines.append("  not saved (the checks failed; --force saves anyway):")
            lines += [f"    {p}" for p in self.withheld]
        if self.advice:
            lines.append("  next:")
            lines += [f"    - {a}" for a in self.advice]
        return lines


class Console(Protocol):
    """How a step talks to its user. ``status`` is a live progress line (each call replaces the last);
    ``ask`` reads one answer and raises EOFError when there is no more input."""

    def say(self, text: str = "") -> None: ...

    def status(self, text: str) -> None: ...

    def ask(self, question: str) -> str: ...


def ask_line(console: Console, question: str) -> str:
    """One line as typed (an Enter alone gives ""). With no more input (stdin closed or at its end) the step
    cannot go on: a CalibrationError naming the question, instead of an EOFError out of the step."""
    try:
        return console.ask(question)
    except EOFError as exc:
        raise CalibrationError(
            f"no answer to {question.strip().rstrip(':').strip()!r}: end of input (stdin is closed)"
        ) from exc


def _ask(console: Console, question: str, default: str | None) -> str:
    prompt = f"{question} [{default}]: " if default is not None else f"{question}: "
    try:
        answer = console.ask(prompt).strip()
    except EOFError as exc:
        if default is not None:
            return default
        raise CalibrationError(f"no answer to {question!r} (end of input)") from exc
    return answer if answer else (default if default is not None else "")


def _ask_parsed(
    console: Console, question: str, default: str | None, parse: Callable[[str], Any], what: str
) -> Any:
    for _ in range(20):
        answer = _ask(console, question, default)
        try:
            return parse(answer)
        except ValueError as exc:
            console.say(f"  {answer!r} is not {what}{': ' + str(exc) if str(exc) else ''}; try again")
    raise CalibrationError(f"no valid answer to {question!r}")


def ask_float(
    console: Console,
    question: str,
    default: float | None = None,
    *,
    minimum: float = -math.inf,
    maximum: float = math.inf,
) -> float:
    """A number from the user, asked again (with the reason) until it parses and is in range."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise ValueError("") from None
        if not math.isfinite(value):
            raise ValueError("it must be finite")
        if not minimum <= value <= maximum:
            raise ValueError(f"it must be between {_fmt(minimum)} and {_fmt(maximum)}")
        return value

    return float(
        _ask_parsed(console, question, None if default is None else _fmt(default), parse, "a number")
    )


def ask_int(
    console: Console, question: str, default: int | None = None, *, minimum: int = 0, maximum: int = 10**9
) -> int:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise ValueError("") from None
        if not minimum <= value <= maximum:
            raise ValueError(f"it must be between {minimum} and {maximum}")
        return value

    return int(
        _ask_parsed(console, question, None if default is None else str(default), parse, "a whole number")
    )


def ask_choice(console: Console, question: str, choices: list[str], default: str) -> str:
    """One of ``choices`` (case-insensitive; a unique prefix is enough)."""

    def parse(text: str) -> str:
        low = text.lower()
        hits = [c for c in choices if c.lower() == low] or [c for c in choices if c.lower().startswith(low)]
        if len(hits) != 1:
            raise ValueError("choose one of " + ", ".join(choices))
        return hits[0]

    return str(_ask_parsed(console, f"{question} ({'/'.join(choices)})", default, parse, "a choice"))


def ask_yes(console: Console, question: str, default: bool = True) -> bool:
    return ask_choice(console, question, ["yes", "no"], "yes" if default else "no") == "yes"
