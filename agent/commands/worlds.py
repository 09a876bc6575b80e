"""Where the shipped example worlds are, for commands that take ``--world``."""

from __future__ import annotations

from pathlib import Path

from agent.shipped import WORLDS
from drivers.errors import ConfigError

EXAMPLES = WORLDS
DEFAULT_WORLD = EXAMPLES / "office.toml"


def resolve_world(path: str | None) -> Path:
    """The world file to load: the given path, or the shipped office world."""
    chosen = Path(path) if path else DEFAULT_WORLD
    if not chosen.is_file():
        if path is None:
            raise ConfigError(
                "--world",
                f"no world given and the default {chosen} is not there; "
                "pass --world FILE (see docs/world.md)",
            )
        raise ConfigError("--world", f"no such world file: {chosen}")
    return chosen
