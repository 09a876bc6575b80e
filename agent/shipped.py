"""Files that ship with the package: the default simulated-robot config and the example worlds.

They live in the repository's top-level ``examples/`` folder; ``agent/examples`` is a symlink to it, so
setuptools packages them as ``agent.examples`` (package data) and an editable install reads them in
place. Code finds them here, through ``importlib.resources``, never relative to the checkout: a wheel or
``pip install .`` has no checkout beside ``site-packages``.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["DEFAULT_SIM_CONFIG", "WORLDS", "shipped"]


def shipped(relative: str) -> Path:
    """The path of a shipped file, ``relative`` to ``examples/`` (e.g. ``"worlds/office.toml"``)."""
    root = resources.files("agent").joinpath("examples", *relative.split("/"))
    # Installed packages are plain folders (pip unpacks wheels), so the Traversable is a real path; the
    # config loader needs one, to resolve the config's relative world path.
    return Path(str(root))


DEFAULT_SIM_CONFIG = shipped("sim.toml")
WORLDS = shipped("worlds")
