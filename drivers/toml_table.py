"""Reading one TOML table with errors that name the key and the file: the base of the config reader
(``agent.config``) and the world-file reader (``drivers.sim.worldfile``).

A :class:`TomlTable` is one table of a parsed TOML document and its dotted key path (``vlp.intrinsics``,
``leds[2]``). Readers take values through it; it remembers which keys were read and which the reader
knows, so that :meth:`TomlTable.finish` can reject a key nobody read and suggest the nearest known one
(``unknown key (did you mean 'baud'?)``). Every mistake is a :class:`~drivers.errors.ConfigError` carrying
the key and the file.
"""

from __future__ import annotations

import difflib
import math
import os
import tomllib
from collections.abc import Mapping
from typing import Any

from drivers.errors import ConfigError

__all__ = ["TomlTable", "as_float", "as_int", "read_toml", "type_name"]


def read_toml(path: str | os.PathLike[str], what: str = "the config file") -> dict[str, Any]:
    """The parsed TOML document at ``path``; a :class:`ConfigError` naming the file (no key) when it cannot
    be read, is not UTF-8 or is not valid TOML. ``what`` names the file in the message ("the bridge
    config")."""
    file = os.fspath(path)
    try:
        with open(file, "rb") as fp:
            return tomllib.load(fp)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError("", f"not valid TOML: {exc}", file) from exc
    except UnicodeDecodeError as exc:
        raise ConfigError("", f"not UTF-8 text: {exc.reason} at byte {exc.start}", file) from exc
    except OSError as exc:
        raise ConfigError("", f"cannot read {what}: {exc.strerror or exc}", file) from exc


def type_name(value: object) -> str:
    """The TOML type of a parsed value, with its article, for messages ("an integer", "a table")."""
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int):
        return "an integer"
    if isinstance(value, float):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, dict):
        return "a table"
    return type(value).__name__


def as_float(value: object, key: str, file: str | None) -> float:
    """A finite number (an integer or a float, not a boolean) as a float."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(key, f"must be a number, not {type_name(value)}", file)
    result = float(value)
    if not math.isfinite(result):
        raise ConfigError(key, f"must be finite, got {value}", file)
    return result


def as_int(value: object, key: str, file: str | None) -> int:
    """An integer (not a boolean)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(key, f"must be an integer, not {type_name(value)}", file)
    return value


class TomlTable:
    """One TOML table and its dotted key path; remembers what was read, to reject unknown keys."""

    def __init__(self, data: Mapping[str, Any], path: str, file: str | None) -> None:
        self.data = data
        self.path = path
        self.file = file
        self.used: set[str] = set()
        self.known: set[str] = set()

    def key(self, name: str) -> str:
        return f"{self.path}.{name}" if self.path else name

    def error(self, name: str, reason: str) -> ConfigError:
        return ConfigError(self.key(name), reason, self.file)

    def expect(self, *names: str) -> None:
        """Names the reader knows, for the "did you mean" hint even when they are absent."""
        self.known.update(names)

    def has(self, name: str) -> bool:
        self.known.add(name)
        return name in self.data

    def take(self, name: str) -> Any:
        self.known.add(name)
        self.used.add(name)
        return self.data[name]

    def finish(self) -> None:
        """Reject keys nobody read, suggesting the closest known one."""
        for name in self.data:
            if name not in self.used:
                close = difflib.get_close_matches(name, sorted(self.known), n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise self.error(name, f"unknown key{hint}")

    def boolean(self, name: str, default: bool) -> bool:
        if not self.has(name):
            return default
        value = self.take(name)
        if not isinstance(value, bool):
            raise self.error(name, f"must be true or false, not {type_name(value)}")
        return value
